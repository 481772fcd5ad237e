"""The dashboard process: bus subscriber (live, drops the oldest frames) + aiohttp server, in one asyncio loop.

It listens to every stage's `control` (heartbeats with counters, EOS, PONG), the dialogue's `dialogue.step`,
the renderer's `render.frame` and the sink's `metrics`, turns them into page events (agent.dashboard.events)
and pushes them to the open pages. Its only publication is `control` from source "dashboard": the page's
START / STOP, and heartbeats. It exits on the supervisor's STOP, on SIGTERM, or when the supervisor dies.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import os
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zmq

from agent.clock import ClockSync
from agent.dashboard.events import (
    BINARY_AUDIO,
    BINARY_FRAME,
    BINARY_MOTION,
    LatencyMeter,
    RunState,
    Transcript,
    frame_jpeg,
    hello_event,
    pack_binary,
    pcm_int16,
    vad_event,
)
from agent.latency import DISPLAY_KEY, to_reference_clock
from agent.process import SupervisorWatch, exit_now, redirect_output
from agent.sections import AppConfig
from agent.stage import SUPERVISOR
from ecas.core.atomic import write_text_atomic
from ecas.core.bus import Publisher, Subscriber, stage_address
from ecas.core.component import RunContext
from ecas.core.messages import (
    Command,
    Control,
    DialogueStep,
    GestureStep,
    Kind,
    Message,
    Metrics,
    MicAudio,
    RenderFrame,
)
from render.motion_wire import encode, motion_packet

log = logging.getLogger("dashboard")

DASHBOARD = "dashboard"
TOPICS = tuple(k.value for k in (Kind.CONTROL, Kind.METRICS, Kind.DIALOGUE_STEP, Kind.GESTURE_STEP, Kind.RENDER_FRAME))
LIVE_QUEUE_MESSAGES = 64  # data messages waiting here; past it the oldest frames are dropped and counted ...
# ... never the words, speech, motion and latencies (small, one per step)
KEPT_TOPICS = (Kind.METRICS.value, Kind.DIALOGUE_STEP.value, Kind.GESTURE_STEP.value)
POLL_S = 0.01
COUNTERS_EVERY_S = 0.5
ORIGINS_KEPT = 250  # steps whose capture time waits for a page's display report (20 s)
URL_FILE = "dashboard.url"
EXIT_STARTUP_FAILED = 3


@dataclass(frozen=True)
class DashboardLaunch:
    """Everything the dashboard process needs; picklable for multiprocessing spawn."""

    app: AppConfig
    run: RunContext
    ipc_dir: Path
    token: str | None = None  # required in every request (a dashboard beyond loopback; agent.dashboard.access)

    @property
    def log_path(self) -> Path:
        return self.run.run_dir / f"{DASHBOARD}.log"


class DashboardBridge:
    """Bus side: reads messages, keeps the page state, hands events, frames and audio to the hub."""

    def __init__(self, launch: DashboardLaunch):
        app = launch.app
        self.cfg, self.live = app.dashboard, launch.run.live
        self.render_mode = app.render.mode
        self.pipeline = tuple(app.run.stages)
        self.session = launch.run.session
        ctx = zmq.Context.instance()
        self.pub = Publisher(ctx, stage_address(DASHBOARD, app.bus, launch.ipc_dir), DASHBOARD, lossless=True)
        addresses = [stage_address(s, app.bus, launch.ipc_dir) for s in (*self.pipeline, SUPERVISOR)]
        self.sub = Subscriber(ctx, addresses, TOPICS, live_queue=LIVE_QUEUE_MESSAGES, keep_topics=KEPT_TOPICS)
        self.transcript = Transcript(self.cfg.max_turns)
        self.latency = LatencyMeter(self.pipeline, self.cfg.history_steps)
        self.run_state = RunState(self.pipeline, self.pipeline[-1], self.cfg.wait_for_start)
        self.clock = ClockSync()
        self.mic_chunks = 0
        self.hub = None  # set by serve()
        self.stopping = False
        self.frames_in = 0
        self.bad_frames = 0
        self.motion_steps = 0
        self.origins: collections.OrderedDict[int, int] = collections.OrderedDict()  # step -> capture time, here
        self.displayed_steps = 0

    def snapshot(self) -> list[dict]:
        return [
            hello_event(self.pipeline, self.live, self.session, self.cfg.browser_mic, self.render_mode),
            self.run_state.event(),
            *self.transcript.snapshot(),
            *self.latency.snapshot(),
            self.counters_event(),
        ]

    def counters_event(self) -> dict:
        own = {
            "received_frames": self.frames_in,
            "dropped": self.sub.dropped,
            "lost": self.sub.lost,
            "decode_errors": self.sub.decode_errors,
            "bad_frames": self.bad_frames,
            "motion_steps": self.motion_steps,
            "displayed_steps": self.displayed_steps,
            "mic_chunks": self.mic_chunks,
            **(self.hub.counters() if self.hub else {}),
        }
        return self.run_state.counters_event(own)

    def command(self, name: str) -> None:
        """A page pressed Start or Stop: tell the supervisor."""
        self.pub.send(Control(command=Command(name), session=self.session))

    def poll(self) -> None:
        """Take everything that arrived and push it to the pages."""
        if self.sub.socket.poll(0, zmq.POLLIN):
            self.sub.poll_into_queue()
        while self.sub.controls:
            self._on_control(self.sub.controls.popleft())
        while self.sub.queue:
            self._on_data(self.sub.queue.popleft())

    def _on_control(self, msg: Control) -> None:
        if msg.command == Command.PONG and "t0" in msg.detail:
            d = msg.detail
            self.clock.add(msg.source, d["t0"], d["t1"], d["t2"], time.monotonic_ns())
        if msg.source == SUPERVISOR and msg.command == Command.STOP:
            self.stopping = True
        for event in self.run_state.on_control(msg):
            self.hub.broadcast(event)

    def _on_data(self, msg: Message) -> None:
        if isinstance(msg, RenderFrame):
            self._on_frame(msg)
        elif isinstance(msg, DialogueStep):
            for event in (*self.transcript.on_step(msg), vad_event(msg)):
                self.hub.broadcast(event)
            if msg.agent_speaking or msg.text_piece:
                self.hub.broadcast_audio(pack_binary(BINARY_AUDIO, msg.step, 0, pcm_int16(msg.agent_pcm)))
        elif isinstance(msg, GestureStep):
            self._on_motion(msg)
        elif isinstance(msg, Metrics):
            for event in self.latency.on_metrics(msg, self.clock.offsets_ns()):
                self.hub.broadcast(event)

    def _on_motion(self, msg: GestureStep) -> None:
        """A step's motion to the pages and clients that asked for it, its times on this host's clock."""
        self.motion_steps += 1
        offsets = self.clock.offsets_ns()
        origin = to_reference_clock(msg.t_origin_ns, self.pipeline[0], offsets) if msg.t_origin_ns else 0
        if origin:
            self.origins[msg.step] = origin
            while len(self.origins) > ORIGINS_KEPT:
                self.origins.popitem(last=False)
        if not self.hub.motion_pages:
            return
        packet = motion_packet(
            msg.step,
            msg.poses,
            msg.trans,
            msg.expressions,
            t_origin_ns=origin,
            t_motion_ns=to_reference_clock(msg.stamps.get("gesture", msg.t_ns), "gesture", offsets),
        )
        self.hub.broadcast_motion(pack_binary(BINARY_MOTION, msg.step, 0, encode(packet)))

    def on_displayed(self, step: int, t_display_ns: float, clock_rtt_ms: float) -> None:
        """A page showed `step`: its latency from capture to the display, to the page's chart and, as a Metrics
        sample, to the run's latency.json (the first page's report of a step counts)."""
        origin = self.origins.pop(step, None)
        if origin is None:
            return
        e2e_ms = round((t_display_ns - origin) / 1e6, 2)
        self.displayed_steps += 1
        self.hub.broadcast({"type": "display_latency", "step": step, "e2e_ms": e2e_ms, "clock_rtt_ms": clock_rtt_ms})
        values = {DISPLAY_KEY: e2e_ms, "clock_rtt_ms": round(clock_rtt_ms, 3)}
        self.pub.send(Metrics(session=self.session, step=step, t_origin_ns=origin, values=values))

    def _on_frame(self, msg: RenderFrame) -> None:
        self.frames_in += 1
        if not self.hub.pages or msg.encoding == "none":  # render.mode browser: the page draws the avatar
            return
        try:
            jpeg = frame_jpeg(msg, self.cfg.jpeg_quality)
        except (ValueError, OSError) as e:
            self.bad_frames += 1
            log.warning("skipped render frame of step %d: %s", msg.step, e)
            return
        self.hub.broadcast_frame(pack_binary(BINARY_FRAME, msg.step, msg.frame_index, jpeg))

    def heartbeat(self) -> None:
        self.pub.send(
            Control(
                command=Command.HEARTBEAT,
                session=self.session,
                detail={"state": "running", "counters": self.counters_event()["dashboard"]},
            )
        )

    def close(self) -> None:
        self.pub.close()
        self.sub.close()

    def send_mic(self, pcm_int16: bytes) -> None:
        """A chunk of the page's microphone, to the io stage over the bus (numbered, so it counts what it lost)."""
        self.pub.send(MicAudio(session=self.session, pcm=np.frombuffer(pcm_int16, "<i2")))
        self.mic_chunks += 1


async def serve(launch: DashboardLaunch, supervisor: SupervisorWatch) -> None:
    from agent.dashboard.server import Hub, make_app, start_server

    bridge = DashboardBridge(launch)
    bridge.hub = Hub(
        bridge.snapshot, bridge.command, bridge.send_mic if bridge.cfg.browser_mic else None, bridge.on_displayed
    )
    supervisor.stop = lambda: setattr(bridge, "stopping", True)
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, supervisor.stop)
    cfg = launch.app.dashboard
    tls = (cfg.tls_cert, cfg.tls_key) if cfg.tls_cert else None
    app = make_app(bridge.hub, cfg.host, launch.token, launch.app.render.avatar)
    runner, port = await start_server(app, cfg.host, cfg.port, tls)
    url = page_url(cfg.host, port, tls is not None, launch.token)
    write_text_atomic(launch.run.run_dir / URL_FILE, url + "\n")
    log.info("serving %s", url)
    next_beat = next_counters = 0.0
    try:
        while not bridge.stopping and os.getppid() != 1:
            bridge.poll()
            now = time.monotonic()
            if now >= next_counters:
                bridge.hub.broadcast(bridge.counters_event())
                next_counters = now + COUNTERS_EVERY_S
            if now >= next_beat:
                bridge.heartbeat()
                next_beat = now + launch.app.bus.heartbeat_s
            await asyncio.sleep(POLL_S)
        bridge.poll()
        await bridge.hub.send_last(bridge.run_state.event())
    finally:
        await bridge.hub.close_pages()
        await runner.cleanup()
        bridge.close()


def page_url(host: str, port: int, tls: bool = False, token: str | None = None) -> str:
    """The address to open (with the dashboard's token, if it has one); a wildcard bind is opened through this
    machine's loopback."""
    shown = {"0.0.0.0": "127.0.0.1", "::": "[::1]", "": "127.0.0.1"}.get(host, host)
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    return f"{'https' if tls else 'http'}://{shown}:{port}/" + (f"?token={token}" if token else "")


def dashboard_main(launch: DashboardLaunch) -> None:
    """The process entry point (multiprocessing spawn target)."""
    from ecas.core.threads import limit_threads

    supervisor = SupervisorWatch(launch.ipc_dir)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the group; the supervisor decides
    redirect_output(launch.log_path)
    logging.basicConfig(
        level=logging.INFO, stream=sys.stderr, format="%(asctime)s dashboard %(levelname)s %(name)s: %(message)s"
    )
    limit_threads()
    try:
        asyncio.run(serve(launch, supervisor))
    except OSError as e:
        log.error("%s", e)
        sys.exit(EXIT_STARTUP_FAILED)
    log.info("stopped")
    exit_now(0)  # without the interpreter's teardown, as the stages do (agent.process.exit_now)
