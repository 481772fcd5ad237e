"""The live dashboard: page events from bus messages, the server, and a real run watched in headless Chromium."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import aiohttp
import numpy as np
import pytest
import soundfile as sf
import zmq
from aiohttp import WSCloseCode
from PIL import Image

from agent.dashboard.browser import HeadlessChromium, find_chromium
from agent.dashboard.config import DashboardConfig
from agent.dashboard.events import (
    AGENT_GAP_STEPS,
    BINARY_FRAME,
    BINARY_HEADER,
    BINARY_MIC,
    LatencyMeter,
    RunState,
    Transcript,
    frame_jpeg,
    level_dbfs,
    pack_binary,
    turn_state,
)
from agent.dashboard.mic import MAX_BUFFER_STEPS, PRIME_STEPS, BrowserMicSource
from agent.dashboard.process import page_url
from agent.dashboard.server import MAX_PENDING_FRAMES, MAX_PENDING_MOTION, Hub, Page, make_app, start_server
from agent.sections import load_app_config
from ecas.core.bus import Publisher
from ecas.core.config import ConfigError, build_dataclass
from ecas.core.messages import Command, Control, DialogueStep, Metrics, MicAudio, RenderFrame, VadState
from ecas.core.paths import DEFAULT_CONFIG, data_root
from ecas.core.timing import STEP_HZ, STEP_SAMPLES
from tests.test_runtime import finish, launch, leftovers

PIPELINE = ("io", "dialogue", "gesture", "render")


def step(n: int, **fields) -> DialogueStep:
    zeros = np.zeros(1920, np.float32)
    codes = np.zeros(8, np.int32)
    return DialogueStep(step=n, agent_pcm=zeros, user_pcm=zeros, agent_codes=codes, user_codes=codes, **fields)


# ---- transcript -------------------------------------------------------------------------------------------------
def test_agent_words_form_a_turn_and_a_barge_in_marks_the_word_being_spoken():
    transcript = Transcript(max_turns=10)
    for n, word in enumerate(["Hello", "there,", "how"]):
        transcript.on_step(step(n, text_piece=word, agent_speaking=True))
    events = transcript.on_step(
        step(3, text_piece="are", agent_speaking=True, agent_interrupted=True, user_vad_state=VadState.SPEAKING)
    )
    assert events == [
        {
            "type": "turn",
            "id": 0,
            "speaker": "agent",
            "start_step": 0,
            "words": ["Hello", "there,", "how", "are"],
            "partial": "",
            "interrupted_at": 3,
            "final": True,
        }
    ]
    (later,) = transcript.on_step(step(4, text_piece="Sure", agent_speaking=True))
    assert (later["id"], later["words"], later["interrupted_at"]) == (1, ["Sure"], None)


def test_sentencepiece_pieces_are_joined_into_words():
    transcript = Transcript(max_turns=10)
    for n, piece in enumerate([" Hel", "lo", " there", ",", " friend"]):
        (event,) = transcript.on_step(step(n, text_piece=piece, agent_speaking=True))
    assert event["words"] == ["Hello", "there,", "friend"]


def test_user_turn_shows_the_partial_hypothesis_until_its_words_are_final():
    transcript = Transcript(max_turns=10)
    assert transcript.on_step(step(0, user_vad_state=VadState.SPEAKING)) == []
    (partial,) = transcript.on_step(step(1, user_partial="what is"))
    assert (partial["speaker"], partial["words"], partial["partial"], partial["final"]) == (
        "user",
        [],
        "what is",
        False,
    )
    assert transcript.on_step(step(2, user_partial="what is")) == []  # unchanged: no event
    (final,) = transcript.on_step(step(3, user_words="what is the time"))
    assert (final["id"], final["words"], final["partial"], final["final"]) == (
        partial["id"],
        ["what", "is", "the", "time"],
        "",
        True,
    )
    assert [t["words"] for t in transcript.snapshot()] == [["what", "is", "the", "time"]]


def test_a_hypothesis_dropped_without_words_removes_its_turn():
    transcript = Transcript(max_turns=10)
    (turn,) = transcript.on_step(step(0, user_partial="uh"))
    assert transcript.on_step(step(1)) == [{"type": "turn_removed", "id": turn["id"]}]
    assert transcript.snapshot() == []


def test_an_agent_turn_ends_after_a_pause_and_turns_are_bounded():
    transcript = Transcript(max_turns=3)
    transcript.on_step(step(0, text_piece="one", agent_speaking=True))
    events = [e for n in range(1, AGENT_GAP_STEPS + 1) for e in transcript.on_step(step(n))]
    assert events == [{**events[-1], "words": ["one"], "final": True}]
    for n in range(5):
        transcript.on_step(step(100 + n * 20, text_piece=f"w{n}"))
        for k in range(AGENT_GAP_STEPS):
            transcript.on_step(step(101 + n * 20 + k))
    assert [t["words"] for t in transcript.snapshot()] == [["w2"], ["w3"], ["w4"]]


def test_turn_state_names_who_holds_the_floor():
    assert turn_state(step(0)) == "none"
    assert turn_state(step(0, agent_speaking=True)) == "agent"
    assert turn_state(step(0, user_vad_state=VadState.STARTING)) == "user"
    assert turn_state(step(0, user_vad_state=VadState.SPEAKING, agent_speaking=True)) == "overlap"


# ---- latency, run state, frames -------------------------------------------------------------------------------
def metrics(n: int, frame_index: int, t0: int = 1_000_000_000) -> Metrics:
    ms = 1_000_000
    stamps = {
        "io": t0 + 1 * ms,
        "dialogue.in": t0 + 2 * ms,
        "dialogue": t0 + 12 * ms,
        "gesture.in": t0 + 13 * ms,
        "gesture": t0 + 23 * ms,
        "render.in": t0 + 24 * ms,
        "render": t0 + 54 * ms,
    }
    return Metrics(step=n, t_origin_ns=t0, stamps=stamps, values={"frame_index": float(frame_index)})


def test_latency_of_a_step_is_split_per_stage_on_its_last_frame():
    meter = LatencyMeter(PIPELINE, history_steps=2)
    assert meter.on_metrics(metrics(0, frame_index=0), {}) == []
    (event,) = meter.on_metrics(metrics(0, frame_index=1), {})
    assert event == {
        "type": "latency",
        "step": 0,
        "e2e_ms": 54.0,
        "stages": {"io": 1.0, "dialogue": 11.0, "gesture": 11.0, "render": 31.0},
    }
    (shifted,) = meter.on_metrics(metrics(1, frame_index=1), {"render": 4_000_000})  # render's clock runs 4 ms ahead
    assert (shifted["e2e_ms"], shifted["stages"]["render"]) == (50.0, 27.0)
    meter.on_metrics(metrics(2, frame_index=1), {})
    assert [e["step"] for e in meter.snapshot()] == [1, 2]


def test_run_phase_follows_the_stages_and_the_supervisor():
    state = RunState(PIPELINE, "render", wait_for_start=True)
    beat = lambda source, s: Control(
        source=source,
        command=Command.HEARTBEAT,
        detail={"state": s, "counters": {"dropped": 2}},
    )
    assert state.phase == "starting"
    events = [e for s in PIPELINE for e in state.on_control(beat(s, "ready"))]
    assert [e["phase"] for e in events] == ["ready"]
    assert state.on_control(Control(source="supervisor", command=Command.START))[0]["phase"] == "running"
    assert state.counters_event({})["stages"]["io"] == {"dropped": 2}
    assert state.on_control(Control(source="render", command=Command.EOS, detail={"handled": 9}))[0]["phase"] == "ended"


def test_raw_frames_are_encoded_to_jpeg_and_jpeg_frames_pass_through():
    rgb = np.zeros((32, 48, 3), np.uint8)
    rgb[:, :24] = (200, 40, 40)
    frame = RenderFrame(width=48, height=32, encoding="rgb24", image=rgb)
    decoded = np.asarray(Image.open(io.BytesIO(frame_jpeg(frame, quality=90))))
    assert decoded.shape == (32, 48, 3)
    assert np.abs(decoded.astype(int) - rgb).mean() < 3
    jpeg = np.frombuffer(frame_jpeg(frame, 90), np.uint8)
    assert frame_jpeg(RenderFrame(width=48, height=32, encoding="jpeg", image=jpeg), 10) == jpeg.tobytes()
    with pytest.raises(ValueError, match="unknown encoding 'png'"):
        frame_jpeg(RenderFrame(width=48, height=32, encoding="png", image=jpeg), 90)


def test_binary_header_carries_kind_frame_index_and_step():
    data = pack_binary(BINARY_FRAME, 70000, 1, b"jpeg")
    assert BINARY_HEADER.size == 8
    assert struct.unpack("<BxHI", data[:8]) == (BINARY_FRAME, 1, 70000) and data[8:] == b"jpeg"


def test_config_errors_name_the_option():
    with pytest.raises(ConfigError, match=r"dashboard.port: must be in \[0, 65535\], got 70000"):
        build_dataclass(DashboardConfig, {"port": 70000}, "dashboard")
    with pytest.raises(ConfigError, match="dashboard.max_turns: must be >= 1"):
        build_dataclass(DashboardConfig, {"max_turns": 0}, "dashboard")
    assert DashboardConfig().loopback_only and DashboardConfig(host="localhost").loopback_only
    assert not DashboardConfig(host="0.0.0.0").loopback_only


def test_launch_flags_for_the_dashboard():
    import launch

    def app(*argv):
        return load_app_config(launch.DEFAULT_CONFIG, launch.mode_overrides(launch.parse_args(argv), None))

    exposed = app("--replay", "talk.wav", "--host", "0.0.0.0")
    assert exposed.dashboard.host == "0.0.0.0" and not exposed.dashboard.loopback_only and exposed.run.live
    mic = app("--browser-mic")
    assert mic.run.components["io"] == "agent.dashboard.mic:browser_io" and mic.dashboard.browser_mic
    assert mic.dashboard.enabled and mic.run.live
    assert not app("--replay", "talk.wav", "--headless").dashboard.enabled
    with pytest.raises(SystemExit):
        launch.parse_args(["--browser-mic", "--headless"])
    with pytest.raises(SystemExit):
        launch.parse_args(["--browser-mic", "--replay", "talk.wav"])


def test_page_url_opens_a_wildcard_bind_through_loopback():
    assert page_url("127.0.0.1", 8998) == "http://127.0.0.1:8998/"
    assert page_url("0.0.0.0", 8998, tls=True) == "https://127.0.0.1:8998/"
    assert page_url("::", 80) == "http://[::1]:80/" and page_url("fe80::1", 80) == "http://[fe80::1]:80/"


# ---- server ---------------------------------------------------------------------------------------------------
def test_server_pushes_snapshot_events_and_frames_and_takes_commands():
    commands = []

    async def scenario():
        hub = Hub(lambda: [{"type": "hello", "pipeline": list(PIPELINE)}], commands.append)
        runner, port = await start_server(make_app(hub), "127.0.0.1", 0)
        try:
            async with aiohttp.ClientSession() as http:
                async with http.get(f"http://127.0.0.1:{port}/") as page:
                    assert page.status == 200 and "dashboard.js" in await page.text()
                async with http.get(f"http://127.0.0.1:{port}/static/dashboard.js") as script:
                    assert script.status == 200
                async with http.ws_connect(f"http://127.0.0.1:{port}/ws") as ws:
                    assert json.loads((await ws.receive()).data)["type"] == "hello"
                    hub.broadcast({"type": "vad", "prob": 0.5})
                    hub.broadcast_frame(pack_binary(BINARY_FRAME, 3, 0, b"\xff\xd8"))
                    assert json.loads((await ws.receive()).data) == {"type": "vad", "prob": 0.5}
                    assert (await ws.receive()).data == pack_binary(BINARY_FRAME, 3, 0, b"\xff\xd8")
                    await ws.send_str(json.dumps({"type": "control", "command": "stop"}))
                    await ws.send_str(json.dumps({"type": "control", "command": "rm -rf"}))
                    await ws.send_str("not json")
                    await ws.send_str("[" * 30_000 + "]" * 30_000)  # deeper than the JSON parser's stack
                    await ws.send_str(json.dumps({"type": "control", "command": "start"}))
                    await _until(lambda: len(commands) == 2)
                    assert not ws.closed  # the page's connection survived the deep message
                with pytest.raises(aiohttp.WSServerHandshakeError):  # another web site's page may not connect
                    await http.ws_connect(f"http://127.0.0.1:{port}/ws", headers={"Origin": "http://evil.test"})
        finally:
            await runner.cleanup()

    asyncio.run(scenario())
    assert commands == ["stop", "start"]


def test_a_port_in_use_gives_a_clear_error():
    async def scenario():
        with socket.socket() as taken:
            taken.bind(("127.0.0.1", 0))
            taken.listen()
            port = taken.getsockname()[1]
            with pytest.raises(OSError, match=f"dashboard: cannot listen on 127.0.0.1:{port}.*dashboard.port"):
                await start_server(make_app(Hub(list, print)), "127.0.0.1", port)

    asyncio.run(scenario())


def test_one_page_at_a_time_holds_the_microphone_and_only_its_audio_is_relayed():
    relayed = []

    async def scenario():
        hub = Hub(list, print, relayed.append)
        runner, port = await start_server(make_app(hub), "127.0.0.1", 0)
        try:
            async with (
                aiohttp.ClientSession() as http,
                http.ws_connect(f"http://127.0.0.1:{port}/ws") as first,
                http.ws_connect(f"http://127.0.0.1:{port}/ws") as second,
            ):
                await second.send_bytes(pack_binary(BINARY_MIC, 0, 0, b"\x01\x00"))  # not claimed: ignored
                await first.send_str(json.dumps({"type": "mic", "enabled": True}))
                assert json.loads((await first.receive()).data) == {"type": "mic", "granted": True, "reason": ""}
                await second.send_str(json.dumps({"type": "mic", "enabled": True}))
                refused = json.loads((await second.receive()).data)
                assert refused["granted"] is False and "another page" in refused["reason"]
                await first.send_bytes(pack_binary(BINARY_MIC, 1, 0, b"\x02\x00\x03\x00"))
                await first.send_bytes(pack_binary(BINARY_MIC, 2, 0, b"\x02\x00\x03"))  # odd length: skipped
                await _until(lambda: relayed)
                await first.close()
                await _until(lambda: hub.mic_page is None)
        finally:
            await runner.cleanup()

    asyncio.run(scenario())
    assert relayed == [b"\x02\x00\x03\x00"]


@contextlib.asynccontextmanager
async def _connected_page(hub: Hub):
    """A page's WebSocket to a dashboard server of `hub` on a free port."""
    runner, port = await start_server(make_app(hub), "127.0.0.1", 0)
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(f"http://127.0.0.1:{port}/ws") as ws:
            yield ws
    finally:
        await runner.cleanup()


def test_agent_audio_reaches_only_pages_that_asked_for_it():
    async def scenario():
        hub = Hub(list, print)
        async with _connected_page(hub) as ws:
            hub.broadcast_audio(b"before")
            await ws.send_str(json.dumps({"type": "audio", "enabled": True}))
            await _until(lambda: all(p.wants_audio for p in hub.pages))
            hub.broadcast_audio(b"after")
            assert (await ws.receive()).data == b"after"

    asyncio.run(scenario())


def test_the_last_event_reaches_a_page_before_the_frames_it_was_behind_on():
    """At the end of a run a page still behind on frames gets the run's last state, and only that, before it is
    closed (it used to be closed after a fixed 0.1 s, which a slow page's backlog can outlast)."""
    last = {"type": "run", "phase": "stopped"}

    async def scenario():
        hub = Hub(list, print)
        async with _connected_page(hub) as ws:
            await _until(lambda: hub.pages)
            for step in range(3):
                hub.broadcast_frame(pack_binary(BINARY_FRAME, step, 0, b"\xff\xd8" * 100_000))
            await hub.send_last(last)
            assert all(page.flushed for page in hub.pages)
            await hub.close_pages()
            received = []
            while (msg := await ws.receive()).type in (aiohttp.WSMsgType.TEXT, aiohttp.WSMsgType.BINARY):
                received.append(msg.data)
            return received

    assert asyncio.run(scenario()) == [json.dumps(last, separators=(",", ":"))]


def test_a_page_still_sending_gets_the_last_event_and_a_clean_close():
    """A page streaming its microphone when the run ends: the dashboard reads it to the end of the close handshake
    before the server shuts down, so the page gets the last state and close code 1000. Before, the connection ended
    while the page's audio still came in; the kernel reset it and the page lost the state it had not read (1006)."""
    last = {"type": "run", "phase": "stopped"}

    async def scenario():
        hub = Hub(list, print)
        runner, port = await start_server(make_app(hub), "127.0.0.1", 0)

        async def end_of_run() -> None:
            await _until(lambda: hub.pages)
            await hub.send_last(last)
            await hub.close_pages()
            await runner.cleanup()

        async with aiohttp.ClientSession() as http, http.ws_connect(f"http://127.0.0.1:{port}/ws") as ws:
            ending = asyncio.ensure_future(end_of_run())
            for _ in range(60):  # 0.3 s of audio blocks, reading nothing meanwhile (a busy page)
                await ws.send_bytes(pack_binary(BINARY_MIC, 0, 0, bytes(4000)))
                await asyncio.sleep(0.005)
            received = []
            while (msg := await ws.receive()).type == aiohttp.WSMsgType.TEXT:
                received.append(msg.data)
            await ending
            return received, ws.close_code

    received, code = asyncio.run(scenario())
    assert received == [json.dumps(last, separators=(",", ":"))] and code == WSCloseCode.GOING_AWAY


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make a certificate")
def test_https_with_a_certificate(tmp_path):
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "1",
            "-subj",
            "/CN=127.0.0.1",
            "-keyout",
            str(key),
            "-out",
            str(cert),
        ],
        check=True,
        capture_output=True,
    )

    async def scenario():
        runner, port = await start_server(make_app(Hub(list, print)), "127.0.0.1", 0, (str(cert), str(key)))
        try:
            async with aiohttp.ClientSession() as http:
                async with http.get(f"https://127.0.0.1:{port}/", ssl=False) as page:
                    assert page.status == 200
        finally:
            await runner.cleanup()

    asyncio.run(scenario())
    with pytest.raises(ConfigError, match="dashboard.tls_cert: tls_cert and tls_key must be given together"):
        build_dataclass(DashboardConfig, {"tls_cert": str(cert)}, "dashboard")


def _mic_source(tmp_path) -> tuple[Publisher, BrowserMicSource]:
    """A dashboard-side publisher on a private ipc path and the io source subscribed to it."""
    address = f"ipc://{tmp_path}/dashboard.sock"
    return Publisher(zmq.Context.instance(), address, "dashboard", lossless=True), BrowserMicSource(address)


def test_browser_mic_source_primes_plays_out_and_bounds_its_buffer(tmp_path):
    publisher, source = _mic_source(tmp_path)
    publisher.close()
    ramp = np.arange(STEP_SAMPLES * 3, dtype=np.float32) / 1e5
    source.add(ramp[:STEP_SAMPLES])
    assert not source.take_step().any()  # one step buffered: not primed yet, silence
    source.add(ramp[STEP_SAMPLES:])
    played = np.concatenate([source.take_step() for _ in range(3)])
    np.testing.assert_array_equal(played, ramp)  # in order, across chunk boundaries
    assert not source.take_step().any() and source.underruns == 1  # ran dry: silence, and primes again
    source.add(np.ones(STEP_SAMPLES * (MAX_BUFFER_STEPS + PRIME_STEPS), np.float32))
    assert source.dropped_samples == STEP_SAMPLES * PRIME_STEPS and source.buffered == MAX_BUFFER_STEPS * STEP_SAMPLES
    source.close()


def test_browser_mic_source_delivers_bus_audio_in_real_time_steps_and_counts_losses(tmp_path):
    publisher, source = _mic_source(tmp_path)
    chunk = (np.full(STEP_SAMPLES, 0.25) * 32767).astype("<i2")
    try:
        blocks = []
        while len(blocks) < 8:
            block = source.next_block(timeout_s=0.005)
            if block is not None:
                blocks.append(block)
                publisher.send(MicAudio(pcm=chunk))
        pcm = np.stack([b[0] for b in blocks])  # (8, STEP_SAMPLES)
        due = np.diff([b[1] for b in blocks])
        assert np.all(due == 80_000_000)  # one step per 80 ms of capture time
        assert not pcm[0].any() and np.allclose(pcm[-1], 0.25, atol=1e-4)
        assert source.counters()["mic_received_samples"] >= STEP_SAMPLES * 4
        assert source.counters()["mic_lost_chunks"] == 0
        publisher._seq[MicAudio.KIND.value] += 3  # three chunks that never arrive
        publisher.send(MicAudio(pcm=chunk))
        while source.counters()["mic_lost_chunks"] == 0:
            source.next_block(timeout_s=0.005)
        assert source.counters()["mic_lost_chunks"] == 3
    finally:
        source.close()
        publisher.close()


def test_level_in_dbfs():
    assert level_dbfs(np.zeros(1920, np.float32)) == -90.0
    assert level_dbfs(np.full(1920, 0.5, np.float32)) == pytest.approx(-6.0, abs=0.1)


async def _until(condition, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.02)


# ---- a real run ------------------------------------------------------------------------------------------------
def test_a_dashboard_port_in_use_is_refused_before_anything_starts(tmp_path):
    wav = tmp_path / "talk.wav"
    sf.write(wav, np.zeros(16000 * 20, np.float32), 16000)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = launch(["--replay", str(wav), "--set", f"dashboard.port={port}"], tmp_path / "run")
        code, output = finish(proc, timeout_s=90)
    assert code == 2, output
    assert output.strip() == (
        f"error: dashboard.port: 127.0.0.1:{port} is in use, perhaps by another run's "
        f"dashboard; set another dashboard.port (0 takes any free port)"
    )
    assert leftovers(proc.pid) == [] and not (tmp_path / "run").exists()


PAGE_STATE = """(() => {
  const video = document.getElementById('video');
  const [r, g, b, a] = video.getContext('2d').getImageData(video.width >> 1, video.height >> 1, 1, 1).data;
  const chart = document.getElementById('chart');
  const px = chart.getContext('2d').getImageData(0, 0, chart.width, chart.height).data;
  let coloured = 0;
  for (let i = 0; i < px.length; i += 4) {
    if (px[i + 3] > 0 && (px[i] !== px[i + 1] || px[i + 1] !== px[i + 2])) coloured++;
  }
  return {...window.dashboard, pixel: [r, g, b, a], chartColoured: coloured,
          transcript: document.getElementById('turns').innerText,
          counters: document.getElementById('counters').innerText,
          phaseText: document.getElementById('phase').textContent};
})()"""


@pytest.mark.skipif(find_chromium() is None, reason="no Chromium browser installed (Debian package `chromium`)")
def test_the_browser_leaves_no_temporary_files(monkeypatch):
    """Chromium's profile and its own temporary directories (singleton socket) go when the page closes."""
    temp = Path(tempfile.mkdtemp(prefix="chr-", dir="/tmp"))  # short: Chromium's socket path must fit 108 bytes
    monkeypatch.setenv("TMPDIR", str(temp))
    monkeypatch.setattr(tempfile, "tempdir", str(temp))

    async def show() -> str:
        async with HeadlessChromium("data:text/html,<p id=p>shown</p>") as page:
            return await page.wait_for("document.getElementById('p')?.textContent", timeout_s=30)

    try:
        assert asyncio.run(show()) == "shown"
        assert list(temp.iterdir()) == []
    finally:
        shutil.rmtree(temp, ignore_errors=True)


@pytest.mark.skipif(
    find_chromium() is None,
    reason="no Chromium browser installed (Debian package `chromium`; `make setup` installs it where it can)",
)
def test_a_live_run_shows_in_headless_chromium(tmp_path):
    """Start and Stop from the page; a rendered frame, the agent's words and a moving latency chart in between."""
    wav = tmp_path / "talk.wav"
    t = np.arange(16000 * 30) / 16000
    sf.write(wav, (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), 16000)
    report = tmp_path / "run"
    proc = launch(["--replay", str(wav), "--set", "dashboard.port=0", "--set", "dashboard.wait_for_start=true"], report)
    (state, later, final_phase), code, output = _drive_page(
        proc, report, lambda url: _watch_page(url, proc), finish_timeout_s=90
    )
    assert code == 0, output
    steps = json.loads((report / "latency.json").read_text())["steps_measured"]
    assert steps < 30 * STEP_HZ / 2, f"Stop did not end the run: {steps} of the recording's {30 * STEP_HZ:.0f} steps"
    assert final_phase == "stopped" and "dashboard: stopped" in (report / "dashboard.log").read_text()
    assert leftovers(proc.pid) == []
    # A rendered frame: the test renderer paints frame of step n in grey level n % 256.
    r, g, b, a = state["pixel"]
    assert state["frames"] > 0 and a == 255
    assert abs(r - state["lastFrameStep"] % 256) <= 4 and abs(r - g) <= 2 and abs(g - b) <= 2
    # The agent's words (the echo dialogue says "w<step>" at every step), from the first step: the page was
    # connected before Start.
    assert state["words"] > 0 and "agent" in state["transcript"] and "w0 w1 w2 w3" in state["transcript"]
    # The latency chart moves.
    assert later["chartLastStep"] > state["chartLastStep"] >= 0
    assert later["chartDraws"] > state["chartDraws"] and later["chartColoured"] > 100
    assert later["latencySamples"] > state["latencySamples"]
    assert "render" in later["counters"] and "dashboard" in later["counters"]
    # Start also turned the agent's voice on: its steps were scheduled as their frames showed.
    assert later["audioSteps"] > 0


async def _watch_page(url: str, proc: subprocess.Popen) -> tuple[dict, dict, str]:
    async with HeadlessChromium(url, 1280, 1000) as page:
        await page.wait_for("window.dashboard && window.dashboard.phase === 'ready'", timeout_s=90)
        assert await page.evaluate("document.getElementById('start').disabled") is False
        await page.evaluate("document.getElementById('start').click()")
        await page.wait_for(
            "window.dashboard.frames >= 4 && window.dashboard.latencySamples >= 2 && window.dashboard.words >= 4"
            " && window.dashboard.chartLastStep >= 0",
            timeout_s=30,
        )
        state = await page.evaluate(PAGE_STATE)
        await page.wait_for(f"window.dashboard.chartLastStep > {state['chartLastStep'] + 3}", timeout_s=20)
        later = await page.evaluate(PAGE_STATE)
        await page.evaluate("document.getElementById('stop').click()")
        deadline = time.monotonic() + 20
        while proc.poll() is None and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        return state, later, await page.evaluate("window.dashboard.phase")


def _wait_for_file(path: Path, proc: subprocess.Popen, timeout_s: float = 60) -> str:
    deadline = time.monotonic() + timeout_s
    while not path.exists() or not path.read_text().strip():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise AssertionError(f"no {path.name}: {finish(proc)[1] if proc.poll() is not None else 'timeout'}")
        time.sleep(0.05)
    return path.read_text()


def _drive_page(proc: subprocess.Popen, report: Path, page_script, finish_timeout_s: float, url_timeout_s: float = 60):
    """Run `page_script(url)` (a coroutine function) against the run's dashboard, then let the run end; the
    process is killed if anything fails. Returns (the script's result, exit code, output)."""
    try:
        url = _wait_for_file(report / "dashboard.url", proc, timeout_s=url_timeout_s).strip()
        result = asyncio.run(page_script(url))
        code, output = finish(proc, timeout_s=finish_timeout_s)
    finally:
        if proc.poll() is None:
            proc.kill()
    return result, code, output


async def _press_stop(page) -> None:
    """Stop the run from the page, which stays open until the run shows it stopped or the dashboard has closed its
    connection (the run is over): a page closed at once can take the command with it before its WebSocket sends
    it (the run then never stops)."""
    await page.evaluate("document.getElementById('stop').click()")
    await page.wait_for(
        "window.dashboard.phase === 'stopped' || document.getElementById('connection').textContent === 'offline'",
        timeout_s=30,
    )


REAL_CLIP = data_root() / "speech" / "librivox_0870.wav"
VIDEO_SPREAD = """(() => {
  const c = document.getElementById('video');
  const px = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let lo = 255, hi = 0;
  for (let i = 0; i < px.length; i += 4) { lo = Math.min(lo, px[i]); hi = Math.max(hi, px[i]); }
  return {spread: hi - lo, width: c.width, transcript: document.getElementById('turns').innerText,
          userWords: [...document.querySelectorAll('.msg.user span')].length,
          agentWords: [...document.querySelectorAll('.msg.agent span:not(.tag)')].length, ...window.dashboard};
})()"""


@pytest.mark.slow
@pytest.mark.skipif(find_chromium() is None, reason="no Chromium browser installed (Debian package `chromium`)")
@pytest.mark.skipif(not REAL_CLIP.exists(), reason=f"needs the shared recording {REAL_CLIP}")
def test_real_dialogue_and_renderer_show_in_the_page(tmp_path):
    """The real stages: dialogue (VAD, ASR, responder, TTS), gesture (when the configured checkpoints are on
    disk; else the test stage) and renderer."""
    root = Path(__file__).resolve().parents[1]
    lm = load_app_config(DEFAULT_CONFIG).gesture.lm_checkpoint
    gesture = (
        []
        if lm is not None and (root / lm).exists()
        else ["--set", "run.components.gesture=tests.components:wave_gesture"]
    )
    report = tmp_path / "run"
    cmd = [
        sys.executable,
        str(root / "launch.py"),
        "--replay",
        str(REAL_CLIP),
        "--report",
        str(report),
        "--set",
        "dashboard.port=0",
        "--set",
        "dashboard.wait_for_start=true",
        *gesture,
    ]
    proc = subprocess.Popen(
        cmd, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )

    async def watch(url: str) -> dict:
        async with HeadlessChromium(url) as page:
            await page.wait_for("window.dashboard && window.dashboard.phase === 'ready'", timeout_s=180)
            await page.evaluate("document.getElementById('start').click()")
            await page.wait_for("document.querySelectorAll('.msg.agent span').length >= 2", timeout_s=60)
            await page.wait_for(
                "window.dashboard.latencySamples > 5 && window.dashboard.frames > 10", timeout_s=60
            )  # wait for the events, do not count them in a window
            return await page.evaluate(VIDEO_SPREAD)

    seen, code, output = _drive_page(proc, report, watch, finish_timeout_s=60)
    assert code == 0, output
    heard = {"john", "dashwood", "leisure", "consider", "power"} & set(seen["transcript"].lower().split())
    assert seen["userWords"] >= 5 and len(heard) >= 2  # pocketsphinx misses about a third of the words
    assert seen["agentWords"] >= 2
    assert seen["frames"] > 10 and seen["spread"] > 100  # the avatar on its backdrop, not a blank canvas
    assert seen["latencySamples"] > 5


FAKE_MIC = ("--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream")


@pytest.mark.skipif(find_chromium() is None, reason="no Chromium browser installed (Debian package `chromium`)")
@pytest.mark.skipif(not REAL_CLIP.exists(), reason=f"needs the shared recording {REAL_CLIP}")
def test_the_pages_microphone_is_the_users_voice(tmp_path):
    """--browser-mic: Chromium's fake microphone plays a real recording; the page sends it, the io stage
    turns it into steps, and the user level the page shows comes back from the dialogue steps."""
    report = tmp_path / "run"
    proc = launch(["--browser-mic", "--set", "dashboard.port=0"], report)
    flags = (*FAKE_MIC, f"--use-file-for-fake-audio-capture={REAL_CLIP}")

    async def talk(url: str) -> dict:
        async with HeadlessChromium(url, flags=flags) as page:
            await page.wait_for("window.dashboard && !document.getElementById('mic').hidden", timeout_s=60)
            silent = await page.wait_for("window.dashboard.frames > 2 && window.dashboard.userDbfs", timeout_s=30)
            await page.evaluate("document.getElementById('mic').click()")
            await page.wait_for("window.dashboard.micBlocks > 25", timeout_s=30)
            loud = await page.wait_for("window.dashboard.userDbfs > -45 && window.dashboard.userDbfs", timeout_s=30)
            counters = await page.evaluate("document.getElementById('micinfo').textContent")
            await _press_stop(page)
            return {"silent": silent, "loud": loud, "micinfo": counters}

    seen, code, output = _drive_page(proc, report, talk, finish_timeout_s=90)
    assert code == 0, output
    assert seen["silent"] == -90.0  # before the microphone: the source delivers silence on time
    assert seen["loud"] > -45 and seen["micinfo"] == ""
    io_counters = json.loads((report / "latency.json").read_text())["counters"]["io"]
    assert io_counters["mic_received_samples"] > 24_000  # more than a second of the page's audio
    assert leftovers(proc.pid) == []


@pytest.mark.slow
@pytest.mark.skipif(find_chromium() is None, reason="no Chromium browser installed (Debian package `chromium`)")
@pytest.mark.skipif(not REAL_CLIP.exists(), reason=f"needs the shared recording {REAL_CLIP}")
def test_the_real_dialogue_answers_the_pages_microphone(tmp_path):
    """--browser-mic with the real dialogue: the recording (then a pause, so the turn ends) is heard, recognised
    and answered. Chromium's fake microphone loops its file."""
    pcm, rate = sf.read(REAL_CLIP, dtype="int16")
    clip = tmp_path / "clip_then_pause.wav"
    sf.write(clip, np.concatenate([pcm, np.zeros(rate * 5, np.int16)]), rate, subtype="PCM_16")
    report = tmp_path / "run"
    cmd = [
        sys.executable,
        str(Path(__file__).resolve().parents[1] / "launch.py"),
        "--browser-mic",
        "--report",
        str(report),
        "--set",
        "dashboard.port=0",
        "--set",
        "run.components.gesture=tests.components:wave_gesture",
    ]
    proc = subprocess.Popen(
        cmd,
        cwd=Path(__file__).resolve().parents[1],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )

    async def talk(url: str) -> str:
        async with HeadlessChromium(url, flags=(*FAKE_MIC, f"--use-file-for-fake-audio-capture={clip}")) as page:
            await page.wait_for(
                "window.dashboard && !document.getElementById('mic').hidden && window.dashboard.frames > 0",
                timeout_s=180,
            )
            await page.evaluate("document.getElementById('mic').click()")
            await page.wait_for("document.querySelectorAll('.msg.agent span').length >= 2", timeout_s=60)
            text = await page.evaluate("document.getElementById('turns').innerText")
            await _press_stop(page)
            return text

    transcript, code, output = _drive_page(proc, report, talk, finish_timeout_s=60, url_timeout_s=180)
    assert code == 0, output
    heard = {"john", "dashwood", "leisure", "consider", "power"} & set(transcript.lower().split())
    assert len(heard) >= 2 and "agent" in transcript  # pocketsphinx misses about a third of the words


def test_the_pages_microphone_reaches_the_io_stage_over_the_bus(tmp_path):
    """The real processes (launch.py --browser-mic: supervisor, dashboard, io and the test stages, on a private ipc
    directory): a client plays the page, claims the microphone and sends int16 chunks over the WebSocket; the io
    stage's counters, as the dashboard reports them, show the audio arrived and no chunk was lost on the way."""
    report = tmp_path / "run"
    proc = launch(["--browser-mic"], report)
    chunk = BINARY_HEADER.pack(BINARY_MIC, 0, 0) + (np.full(STEP_SAMPLES, 0.25) * 32767).astype("<i2").tobytes()
    wanted = 12 * STEP_SAMPLES

    async def page(url: str) -> dict:
        async with aiohttp.ClientSession() as http, http.ws_connect(url.split("?")[0].rstrip("/") + "/ws") as ws:
            await ws.send_str(json.dumps({"type": "mic", "enabled": True}))
            io = {}
            deadline = time.monotonic() + 120  # a guard against a hang: the test waits for the event, not the time
            while io.get("mic_received_samples", 0) < wanted:
                assert time.monotonic() < deadline, f"the io stage never reported the page's audio: {io}"
                await ws.send_bytes(chunk)  # like a microphone, it sends on until the stage has heard enough
                msg = await ws.receive(timeout=30)
                event = json.loads(msg.data) if msg.type == aiohttp.WSMsgType.TEXT else {}
                if event.get("type") == "mic":
                    assert event["granted"], event
                if event.get("type") == "counters":
                    io = event["stages"].get("io", {})
            await ws.send_str(json.dumps({"type": "control", "command": "stop"}))
            return io

    io, code, output = _drive_page(proc, report, page, finish_timeout_s=60)
    assert code == 0, output
    assert io["mic_received_samples"] >= wanted and io["mic_lost_chunks"] == 0 and io["mic_bad_chunks"] == 0
    assert leftovers(proc.pid) == []


def test_a_page_behind_keeps_the_newest_frames_and_motion_and_counts_what_it_skipped():
    page = Page(ws=None)  # nothing is sent: only its queues are filled
    for i in range(MAX_PENDING_FRAMES + 3):
        page.push_frame(bytes([i]))
    for i in range(MAX_PENDING_MOTION + 5):
        page.push_motion(bytes([i]))
    assert page.skipped_frames == 3 and list(page.frames) == [bytes([i]) for i in range(3, MAX_PENDING_FRAMES + 3)]
    assert page.skipped_motion == 5 and list(page.motion)[0] == bytes([5]) and len(page.motion) == MAX_PENDING_MOTION
    assert page.wake.is_set()
