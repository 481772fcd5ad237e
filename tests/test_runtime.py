"""The real processes, started by launch.py on a private ipc path, with small test components."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from bench.procfs import session_pids
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES
from tests import components
from tests.components import TEST_STAGES

ROOT = Path(__file__).resolve().parents[1]
TAIL_S = 0.32  # 4 steps of silence after the recording


@pytest.fixture
def talk(tmp_path) -> tuple[Path, int]:
    """A 1.2 s recording at 16 kHz and the number of steps it makes with the tail."""
    path = tmp_path / "talk.wav"
    t = np.arange(int(1.2 * 16000)) / 16000
    sf.write(path, (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), 16000)
    n_samples = int(1.2 * SAMPLE_RATE_HZ) + int(round(TAIL_S * SAMPLE_RATE_HZ))
    return path, -(-n_samples // STEP_SAMPLES)


def launch(args: list[str], report: Path, env: dict | None = None, **kw) -> subprocess.Popen:
    """launch.py with the test stages and a dashboard on any free port (tests may run beside another run);
    an option in `args` wins over these (a later --set wins)."""
    cmd = [
        sys.executable,
        str(ROOT / "launch.py"),
        *TEST_STAGES,
        "--set",
        f"io.tail_silence_s={TAIL_S}",
        "--set",
        "dashboard.port=0",
        *args,
        "--report",
        str(report),
    ]
    return subprocess.Popen(
        cmd,
        cwd=ROOT,
        env={**os.environ, **(env or {})},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        **kw,
    )


def finish(proc: subprocess.Popen, timeout_s: float = 120) -> tuple[int, str]:
    out, err = proc.communicate(timeout=timeout_s)
    return proc.returncode, out + err


def received(report: Path, topic: str) -> list[dict]:
    rows = [json.loads(line) for line in (report / "received.jsonl").read_text().splitlines()]
    return [r for r in rows if r["topic"] == topic]


def leftovers(sid: int, grace_s: float = 3.0) -> list[str]:
    """Processes of the session still alive after a grace period for the kernel to reap exiting ones."""
    deadline = time.monotonic() + grace_s
    while session_processes(sid) and time.monotonic() < deadline:
        time.sleep(0.05)
    return session_processes(sid)


def session_processes(sid: int) -> list[str]:
    """Command lines of the processes still alive in the run's session (launch.py and every stage share it)."""
    alive = []
    for pid in session_pids(sid):
        try:
            alive.append(Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode())
        except OSError:
            continue  # it exited meanwhile
    return alive


@pytest.mark.parametrize("mode", ["--fast", "--live"])
def test_every_step_arrives_once_in_order(talk, tmp_path, mode):
    wav, n_steps = talk
    live = ["--set", "dashboard.enabled=false", "--set", "bus.live_queue_steps=64"]  # room for a stall of the host
    args = ["--replay", str(wav)] + (["--fast"] if mode == "--fast" else live)
    code, output = finish(launch(args, tmp_path / "run"))
    assert code == 0, output
    for topic in ("dialogue.step", "gesture.step"):
        assert [r["step"] for r in received(tmp_path / "run", topic)] == list(range(n_steps))
    # the sink heard the io stage's clock offset once, on START: one host, one clock
    assert [r["origin_offset_ns"] for r in received(tmp_path / "run", "clock")] == [0]
    latency = json.loads((tmp_path / "run" / "latency.json").read_text())
    assert latency["steps_measured"] == n_steps
    assert all(c.get("dropped", 0) == 0 and c.get("lost", 0) == 0 for c in latency["counters"].values())
    assert {"p50", "p95", "p99", "max"} <= set(latency["end_to_end_ms"])
    assert (tmp_path / "run" / "latency.png").stat().st_size > 0


def test_offline_never_drops_when_the_renderer_is_ten_times_slower(talk, tmp_path):
    wav, n_steps = talk
    env = {components.RENDER_SLEEP_S: "0.04"}  # 2 frames × 40 ms per 80 ms step, ~10× the other stages
    code, output = finish(
        launch(["--replay", str(wav), "--fast", "--set", "bus.credit_window_steps=3"], tmp_path / "run", env)
    )
    assert code == 0, output
    rows = received(tmp_path / "run", "gesture.step")
    assert [r["step"] for r in rows] == list(range(n_steps))
    # The credit window bounds what is in flight: step n is only captured after step n-4 was rendered.
    captured = {r["step"]: r["t_origin_ns"] for r in rows}
    rendered = {r["step"]: r["t_done_ns"] for r in rows}
    assert all(captured[n] >= rendered[n - 4] for n in range(4, n_steps))


def test_a_stage_that_dies_is_named_and_the_run_stops(talk, tmp_path):
    wav, _ = talk
    proc = launch(["--replay", str(wav), "--fast"], tmp_path / "run", {components.KILL_AT_STEP: "5"})
    code, output = finish(proc)
    assert code == 1
    assert "stage 'dialogue' died (exit code -9)" in output
    assert leftovers(proc.pid) == []


def test_sigint_stops_every_process_and_removes_ipc_files(tmp_path):
    wav = tmp_path / "long.wav"
    sf.write(wav, np.zeros(16000 * 30, np.float32), 16000)
    proc = launch(["--replay", str(wav), "--set", "dashboard.enabled=false"], tmp_path / "run")
    _wait_for(lambda: "ready" in _read(tmp_path / "run" / "render.log"), 90)
    time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C does: the whole foreground group gets it
    t0 = time.monotonic()
    code, output = finish(proc, 30)
    stopped_s = time.monotonic() - t0
    assert code == 130, output
    assert leftovers(proc.pid) == []
    ipc_dir = Path(re.search(r"\(bus: (\S+)\)", output).group(1))
    assert ipc_dir.name.startswith("ecas-") and not ipc_dir.exists()
    print(f"stopped in {stopped_s:.2f} s")


def test_a_malformed_frame_is_skipped_and_the_run_goes_on(talk, tmp_path):
    wav, n_steps = talk
    code, output = finish(launch(["--replay", str(wav), "--fast"], tmp_path / "run", {components.CORRUPT_AT_STEP: "3"}))
    assert code == 0, output
    steps = [r["step"] for r in received(tmp_path / "run", "gesture.step")]
    assert steps == [s for s in range(n_steps) if s != 3]
    counters = json.loads((tmp_path / "run" / "latency.json").read_text())["counters"]
    assert counters["gesture"]["decode_errors"] == 1
    assert "skipped a malformed frame" in _read(tmp_path / "run" / "gesture.log")


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


def _wait_for(predicate, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not reached")
        time.sleep(0.1)


def _free_port_block(n: int) -> int:
    import socket

    for base in range(20000, 40000, 97):
        try:
            socks = []
            for port in range(base, base + n):
                sock = socket.socket()
                socks.append(sock)
                sock.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
        finally:
            for sock in socks:
                sock.close()
    raise RuntimeError("no free ports")


def test_stages_split_across_two_launchers_over_tcp(talk, tmp_path):
    """A main host (io, render, supervisor) and a worker host (dialogue, gesture) on loopback tcp."""
    wav, n_steps = talk
    tcp = ["--set", "bus.transport=tcp", "--set", f"bus.base_port={_free_port_block(6)}"]
    worker = launch(
        ["--replay", str(wav), "--fast", "--worker", "--set", "run.spawn=[dialogue, gesture]", *tcp],
        tmp_path / "worker",
    )
    main = launch(["--replay", str(wav), "--fast", "--set", "run.spawn=[io, render]", *tcp], tmp_path / "main")
    code, output = finish(main)
    worker_code, worker_output = finish(worker)
    assert code == 0, output
    assert worker_code == 0, worker_output
    assert [r["step"] for r in received(tmp_path / "main", "gesture.step")] == list(range(n_steps))
    latency = json.loads((tmp_path / "main" / "latency.json").read_text())
    assert set(latency["clock_offsets"]) == {"io", "dialogue", "gesture", "render"}
    assert all(abs(c["offset_ns"]) <= c["uncertainty_ns"] + 1_000_000 for c in latency["clock_offsets"].values())
    assert (tmp_path / "worker" / "gesture.log").exists() and not (tmp_path / "main" / "gesture.log").exists()
