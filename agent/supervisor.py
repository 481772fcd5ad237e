"""Starts every stage as its own OS process, watches them, and stops them all, cleanly and fast.

Startup: spawn, wait until every stage reports READY (it has heard all its publishers), measure each stage's
clock offset (NTP-style PING/PONG), then START. Running: collect heartbeats, latency samples and counters.
A stage that dies or stops beating ends the run with its name, exit code and the tail of its log; so does a
stage that reports a failure (e.g. its MP4 cannot be written), in one line, and one that publishes nothing for
`bus.stall_timeout_s` while its upstream stage is ahead of it.
Stop: STOP on the bus to every process at once (a stage still loading its models, which cannot hear it, gets
SIGTERM at once), then SIGTERM, then SIGKILL, all within `bus.stop_timeout_s` + 0.5 s; the partial files
the stages reported are removed (a killed stage cannot remove its own), and so is the private ipc directory.
The directory is named `ecas-<supervisor pid>-*`: when the launcher is killed its processes remove it
(agent.process.SupervisorWatch), and should they be killed too, the next run removes it once that pid is gone.
"""

from __future__ import annotations

import io
import logging
import multiprocessing as mp
import os
import shutil
import signal
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from agent.clock import ClockSync
from agent.dashboard.launcher import DASHBOARD, DashboardProcess
from agent.latency import LatencyRecorder
from agent.process import COMPONENT_FACTORIES, StageLaunch, stage_main
from agent.sections import AppConfig
from agent.stage import SUPERVISOR
from ecas.core.bus import Publisher, Subscriber, address_option, beyond_loopback, stage_address
from ecas.core.component import RunContext
from ecas.core.messages import Command, Control, Kind, Log, Metrics
from ecas.core.timing import STEP_MS

log = logging.getLogger("supervisor")

LOG_TAIL_LINES = 12
KILL_GRACE_S = 0.5
PAUSE_MIN_S = 1.0  # a gap this long in the supervisor's own loop (which never blocks 0.1 s) means it was stopped
IPC_DIR_PREFIX = "ecas-"


class RunFailed(RuntimeError):
    pass


@dataclass
class StageStatus:
    process: mp.Process | None  # None: the stage runs on another host (`launch.py --worker`)
    state: str = "starting"
    heard: bool = False  # it has sent a heartbeat: its runner is up and acts on STOP
    last_beat_s: float = field(default_factory=time.monotonic)
    counters: dict = field(default_factory=dict)
    error: str | None = None  # the failure the stage reported
    partial_files: tuple[str, ...] = ()  # files it is writing under a temporary name
    progress_step: int = -1
    progress_s: float = field(default_factory=time.monotonic)  # when progress_step last moved


class PauseClock:
    """Silence measured against the supervisor's own loop, which a stopped process cannot fool.

    The loop observes the monotonic clock every few ms. A gap beyond `PAUSE_MIN_S` means the supervisor itself
    was not running (Ctrl-Z and `fg` on the whole run, SIGSTOP/SIGCONT of its process group, a machine too loaded
    to schedule it): the stages were most likely stopped with it, so their silence in that gap is not theirs.
    After such a gap the stages get `grace_s` to beat again before any is called unresponsive. A single stopped
    stage leaves no gap in this loop and is named after the usual timeout.
    """

    def __init__(self, grace_s: float):
        self.grace_s = grace_s
        self.last_s = time.monotonic()
        self.grace_until_s = 0.0
        self.paused_s = 0.0  # total time the supervisor was away

    def observe(self) -> float:
        """The gap since the last observation if it was a pause, else 0."""
        now = time.monotonic()
        gap, self.last_s = now - self.last_s, now
        if gap < PAUSE_MIN_S:
            return 0.0
        self.paused_s += gap
        self.grace_until_s = now + self.grace_s
        return gap

    def reset(self) -> None:
        """After work that blocks the loop on purpose (spawning the stages)."""
        self.last_s = time.monotonic()

    def in_grace(self, now: float) -> bool:
        return now < self.grace_until_s


class Supervisor:
    def __init__(self, app: AppConfig, run: RunContext):
        self.app, self.run_ctx, self.pipeline = app, run, tuple(app.run.stages)
        self.factories = {**COMPONENT_FACTORIES, **app.run.components}
        remove_dead_runs_ipc_dirs()
        self.ipc_dir = Path(tempfile.mkdtemp(prefix=f"{IPC_DIR_PREFIX}{os.getpid()}-"))
        self.stages: dict[str, StageStatus] = {}
        self.latency = LatencyRecorder(self.pipeline)
        self.clock = ClockSync()
        self.pause = PauseClock(app.bus.heartbeat_timeout_s)
        self.interrupted = False
        self.error: str | None = None
        self.sink_done = False
        self.started_s: float | None = None  # START sent
        self.finished_s: float | None = None  # the sink's end of stream
        self.dashboard: DashboardProcess | None = None

    # ---- lifecycle -------------------------------------------------------------------------------------------
    def run(self) -> int:
        """0 when the stream ended, 130 when interrupted, 1 when a stage failed."""
        previous = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
        self.pub = self.sub = None
        try:
            self._open_bus()
            self._spawn()
            for phase in (self._wait_ready, self._sync_clocks, self._wait_for_start, self._start, self._watch):
                if self.interrupted:  # Ctrl-C or SIGTERM during the start-up: straight to the stop
                    break
                phase()
        except RunFailed as e:
            self.error = str(e)
        finally:
            self._stop_all()
            self._remove_partial_files()
            for socket in (self.pub, self.sub):
                if socket is not None:
                    socket.socket.setsockopt(zmq.LINGER, 0)  # every process is gone: nothing left to deliver
                    socket.close()
            shutil.rmtree(self.ipc_dir, ignore_errors=True)
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if self.error:
            log.error("%s", self.error)
            return 1
        return 130 if self.interrupted else 0

    def _open_bus(self) -> None:
        ctx = zmq.Context.instance()
        address = stage_address(SUPERVISOR, self.app.bus, self.ipc_dir)
        try:
            self.pub = Publisher(ctx, address, SUPERVISOR, lossless=True)
        except zmq.ZMQError as e:
            raise RunFailed(
                f"the supervisor cannot listen on {address} ({e}); change bus.base_port or bus.endpoints.supervisor"
            ) from None
        addresses = [stage_address(s, self.app.bus, self.ipc_dir) for s in self.pipeline]
        self.dashboard = DashboardProcess.start(self.app, self.run_ctx, self.ipc_dir)
        warn_public_listeners(self._listeners(), self.app)
        addresses += [self.dashboard.address] if self.dashboard else []
        self.sub = Subscriber(
            ctx, addresses, [k.value for k in (Kind.CONTROL, Kind.METRICS, Kind.LOG)], live_queue=None
        )

    def _listeners(self) -> dict[str, str]:
        """Every bus endpoint this host binds: its stages, the supervisor and the dashboard."""
        names = [*self.app.run.local_stages, SUPERVISOR] + ([DASHBOARD] if self.dashboard else [])
        return {name: stage_address(name, self.app.bus, self.ipc_dir) for name in names}

    def _bus_description(self) -> str:
        listeners = self._listeners()
        if all(address.startswith("ipc://") for address in listeners.values()):
            return str(self.ipc_dir)
        return ", ".join(f"{name} {address}" for name, address in listeners.items())

    def _on_signal(self, signum, _frame) -> None:
        self.interrupted = True

    def _spawn(self) -> None:
        local = spawn_stages(self.app, self.run_ctx, self.ipc_dir, self.factories)
        self.stages = {stage: StageStatus(local.get(stage)) for stage in self.pipeline}
        threading.Thread(target=warm_up_plotting, name="warm-up-plotting", daemon=True).start()
        self.pause.reset()

    # ---- phases ----------------------------------------------------------------------------------------------
    def _wait_ready(self) -> None:
        deadline = time.monotonic() + self.app.bus.ready_timeout_s
        while not all(s.state == "ready" for s in self.stages.values()):
            self._tick()
            if self.interrupted:
                return
            if time.monotonic() > deadline:
                late = [n for n, s in self.stages.items() if s.state != "ready"]
                raise RunFailed(
                    f"stage(s) {', '.join(late)} not ready after {self.app.bus.ready_timeout_s:.0f} s"
                    f"; see {self.run_ctx.run_dir}/<stage>.log"
                )

    def _sync_clocks(self, rounds: int = 5) -> None:
        for _ in range(rounds):
            for stage in self.pipeline:
                self._send(Command.PING, {"to": stage, "t0": time.monotonic_ns()})
            self._tick(0.02)

    def _wait_for_start(self) -> None:
        """`dashboard.wait_for_start`: the run starts when the page's Start button is pressed."""
        if self.dashboard and self.app.dashboard.wait_for_start:
            log.info("waiting for Start on the dashboard")
            while not (self.interrupted or self.dashboard.start_requested or self.dashboard.stop_requested):
                self._tick()

    def _start(self) -> None:
        self._send(Command.START, {"clock_offsets_ns": self.clock.offsets_ns()})
        self.started_s = time.monotonic()
        log.info("started: %s (bus: %s)", " → ".join(self.pipeline), self._bus_description())

    def _watch(self) -> None:
        while not (self.interrupted or self.sink_done or (self.dashboard and self.dashboard.stop_requested)):
            self._tick()

    def _tick(self, duration_s: float = 0.05) -> None:
        """Beat, receive for up to `duration_s`, and check every process."""
        self._send(Command.HEARTBEAT)
        end = time.monotonic() + duration_s
        while True:
            remaining_ms = int(max(0.0, end - time.monotonic()) * 1000)
            if self.sub.socket.poll(remaining_ms, zmq.POLLIN):
                self.sub.poll_into_queue()
            self._observe_pause()
            self._consume()
            if time.monotonic() >= end:
                break
        self._observe_pause()
        self._check_processes()

    def _observe_pause(self) -> None:
        """A pause of the supervisor: what the stages did not do in it is not held against them (PauseClock)."""
        gap_s = self.pause.observe()
        if not gap_s:
            return
        for status in self.stages.values():
            status.progress_s += gap_s  # the stall check counts from the resumption
        log.log(
            logging.INFO if gap_s > 2 * PAUSE_MIN_S else logging.DEBUG,
            "the supervisor was paused for %.1f s (Ctrl-Z, SIGSTOP or an overloaded machine); the stages have "
            "%.0f s to beat again",
            gap_s,
            self.pause.grace_s,
        )

    def _consume(self) -> None:
        while self.sub.controls:
            self._on_control(self.sub.controls.popleft())
        while self.sub.queue:
            msg = self.sub.queue.popleft()
            if isinstance(msg, Metrics):
                self.latency.add(msg, self.clock.offsets_ns())
            elif isinstance(msg, Log):
                log.log(logging.getLevelName(msg.level.upper()), "[%s] %s", msg.source, msg.text)

    def _on_control(self, msg: Control) -> None:
        if self.dashboard and msg.source == DASHBOARD:
            self.dashboard.on_control(msg)  # the page's Start / Stop
            return
        status = self.stages.get(msg.source)
        if status is None:
            return
        status.last_beat_s = time.monotonic()
        status.heard = True
        if msg.command == Command.HEARTBEAT:
            status.state = msg.detail.get("state", status.state)
            status.counters = msg.detail.get("counters", status.counters)
            status.error = status.error or msg.detail.get("error")
            status.partial_files = tuple(msg.detail.get("partial_files", status.partial_files))
            if status.counters.get("progress_step", -1) != status.progress_step:
                status.progress_step = status.counters.get("progress_step", -1)
                status.progress_s = status.last_beat_s
        elif msg.command == Command.PONG:
            self.clock.add(msg.source, msg.detail["t0"], msg.detail["t1"], msg.detail["t2"], time.monotonic_ns())
        elif msg.command == Command.EOS:
            status.counters = msg.detail
            if msg.source == self.pipeline[-1]:
                self.sink_done = True
                self.finished_s = time.monotonic()

    def _check_processes(self) -> None:
        if self.interrupted:
            return  # a SIGTERM to the whole group may have ended a process first: the stop is under way, not a failure
        now = time.monotonic()
        if self.dashboard and self.dashboard.process.exitcode is not None:
            raise RunFailed(
                f"the dashboard died (exit code {self.dashboard.process.exitcode}). Last lines of its "
                f"log:\n{_tail(self.dashboard.log_path)}"
            )
        for name, status in self.stages.items():
            code = status.process.exitcode if status.process else None
            if code is not None:
                raise RunFailed(
                    f"stage '{name}' died (exit code {code}). Last lines of its log:\n"
                    f"{_tail(self.run_ctx.run_dir / f'{name}.log')}"
                )
            if status.error is not None:
                raise RunFailed(f"stage '{name}' failed: {status.error}")
            silent_s = now - status.last_beat_s
            if (
                status.state != "starting"
                and silent_s > self.app.bus.heartbeat_timeout_s
                and not self.pause.in_grace(now)
            ):
                raise RunFailed(f"stage '{name}' stopped responding (no heartbeat for {silent_s:.1f} s)")
        self._check_progress(now)

    def _check_progress(self, now: float) -> None:
        """A stage that publishes nothing while its upstream stage is ahead of it has stalled."""
        if self.started_s is None:
            return
        for upstream, name in zip(self.pipeline, self.pipeline[1:]):
            status, ahead = self.stages[name], self.stages[upstream]
            idle_s = now - max(status.progress_s, self.started_s)
            if (
                status.state == "running"
                and ahead.progress_step > status.progress_step
                and idle_s > self.app.bus.stall_timeout_s
            ):
                raise RunFailed(
                    f"stage '{name}' made no progress for {idle_s:.0f} s while its input waited "
                    f"(it got to step {status.progress_step}, '{upstream}' to step "
                    f"{ahead.progress_step}; bus.stall_timeout_s={self.app.bus.stall_timeout_s:g}); "
                    f"see {self.run_ctx.run_dir / f'{name}.log'}"
                )

    # ---- stopping --------------------------------------------------------------------------------------------
    def _send(self, command: Command, detail: dict | None = None) -> None:
        self.pub.send(Control(command=command, detail=detail or {}))

    def _stop_all(self) -> None:
        """STOP to every process at once; each finishes its step, closes (writes its report files) and exits.

        A stage still loading its models cannot hear STOP and has written nothing: it gets SIGTERM at once, so
        Ctrl-C during the start-up does not wait `bus.stop_timeout_s` for it. Whatever is alive at the deadline
        gets SIGTERM, then SIGKILL (`terminate`).
        """
        if self.pub is None:
            return
        deadline = time.monotonic() + self.app.bus.stop_timeout_s
        self._send(Command.STOP)
        loading = [s.process for s in self.stages.values() if s.process and not s.heard]
        terminate(loading, grace_s=None)
        processes = [s.process for s in self.stages.values() if s.process]
        processes += [self.dashboard.process] if self.dashboard else []
        while any(p.is_alive() for p in processes) and time.monotonic() < deadline:
            self.sub.socket.poll(20, zmq.POLLIN) and self.sub.poll_into_queue()
            self._consume()
            self._send(Command.STOP)
        terminate(processes)
        self.sub.poll_into_queue()
        self._consume()

    def _remove_partial_files(self) -> None:
        """A stage that was killed while writing cannot remove its temporary file; a clean one already has."""
        for name, status in self.stages.items():
            for path in status.partial_files if status.process is not None else ():
                if Path(path).exists():
                    Path(path).unlink(missing_ok=True)
                    log.info("removed %s's partial file %s", name, path)

    def stream_timing(self) -> dict:
        """Wall time from START to the sink's end of stream, against the audio it carried."""
        if self.started_s is None or self.finished_s is None:
            return {}
        wall_s = self.finished_s - self.started_s
        audio_s = self.stages["io"].counters.get("sent_steps", 0) * STEP_MS / 1000
        return {"stream_wall_s": round(wall_s, 3), "audio_s": audio_s, "realtime_factor": round(audio_s / wall_s, 3)}

    def counters(self) -> dict[str, dict]:
        return {name: status.counters for name, status in self.stages.items()}


def warm_up_plotting() -> None:
    """Import matplotlib (Agg) and draw one small figure while the stages load their models, not after Ctrl-C.

    The report's latency.png is drawn once every process has stopped. The import alone took 0.8 s idle and
    1.5-2 s on a loaded 2-core machine, and the first figure another 0.9 s there (the font manager, the first
    text drawn, the PNG writer); later figures take half a second. Runs in a daemon thread; a failure here is
    only logged, and the report's own plot says what is wrong.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(2, 1))
        ax.plot([0, 1], [0, 1], label="warm-up")
        ax.set(xlabel="x", ylabel="y", title="warm-up")
        ax.legend()
        fig.tight_layout()
        fig.savefig(io.BytesIO(), dpi=30, format="png")
        plt.close(fig)
    except Exception:
        log.debug("matplotlib did not warm up in the background", exc_info=True)


def warn_public_listeners(listeners: dict[str, str], app: AppConfig) -> None:
    """One warning, naming the option, for every bus endpoint other machines can reach."""
    for name, address in listeners.items():
        if beyond_loopback(address):
            log.warning(
                "bus: %s listens on %s (%s): anyone who can reach this machine can read the conversation on it "
                "and send messages into the run; keep it on 127.0.0.1 unless the run spans hosts",
                name,
                address,
                address_option(name, app.bus),
            )


def spawn_stages(app: AppConfig, run: RunContext, ipc_dir: Path, factories: dict[str, str]) -> dict[str, mp.Process]:
    """Start this host's stages (`run.spawn`, default all), each in its own spawned process."""
    ctx = mp.get_context("spawn")
    processes = {}
    for stage in app.run.local_stages:
        launch = StageLaunch(stage, tuple(app.run.stages), app, run, ipc_dir, factories[stage])
        processes[stage] = ctx.Process(target=stage_main, args=(launch,), name=f"stage-{stage}")
        processes[stage].start()
    return processes


def terminate(processes: list[mp.Process], grace_s: float | None = KILL_GRACE_S) -> None:
    """SIGTERM what is still alive, then SIGKILL after `grace_s` (None: SIGTERM only, no waiting)."""
    for process in processes:
        if process.is_alive():
            process.terminate()
    if grace_s is None:
        return
    kill_at = time.monotonic() + grace_s
    for process in processes:
        process.join(max(0.0, kill_at - time.monotonic()))
    for process in processes:
        if process.is_alive():
            process.kill()
            process.join(1.0)


def run_worker(app: AppConfig, run: RunContext) -> int:
    """`launch.py --worker`: start this host's stages and wait; the supervisor on the main host drives them."""
    stop = []
    previous = {sig: signal.signal(sig, lambda *_: stop.append(1)) for sig in (signal.SIGINT, signal.SIGTERM)}
    ipc_dir = Path(tempfile.gettempdir())
    warn_public_listeners({s: stage_address(s, app.bus, ipc_dir) for s in app.run.local_stages}, app)
    processes = spawn_stages(app, run, ipc_dir, {**COMPONENT_FACTORIES, **app.run.components})
    log.info("worker running %s; waiting for the supervisor", ", ".join(processes))
    try:
        while not stop and any(p.is_alive() for p in processes.values()):
            time.sleep(0.1)
    finally:
        terminate(list(processes.values()))
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    failed = {name: p.exitcode for name, p in processes.items() if p.exitcode not in (0, None)}
    for name, code in failed.items():
        log.error("stage '%s' exited with code %s; see %s", name, code, run.run_dir / f"{name}.log")
    return 130 if stop else (1 if failed else 0)


def remove_dead_runs_ipc_dirs(tmp_dir: Path | None = None) -> list[Path]:
    """Remove `ecas-<pid>-*` directories of this user whose supervisor process no longer exists.

    A live run's directory is never touched: its pid exists (a recycled pid only delays the clean-up).
    """
    removed = []
    for path in Path(tmp_dir or tempfile.gettempdir()).glob(f"{IPC_DIR_PREFIX}*-*"):
        pid = path.name[len(IPC_DIR_PREFIX) :].split("-", 1)[0]
        try:
            if not pid.isdigit() or path.is_symlink() or path.stat().st_uid != os.getuid() or _alive(int(pid)):
                continue
        except FileNotFoundError:
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    if removed:
        log.info(
            "removed %d socket director%s of runs that ended without cleaning up",
            len(removed),
            "y" if len(removed) == 1 else "ies",
        )
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _tail(path: Path, lines: int = LOG_TAIL_LINES) -> str:
    try:
        text = path.read_text(errors="replace").splitlines()
    except FileNotFoundError:
        return "    (no log written)"
    return "\n".join("    " + line for line in (deque(text, maxlen=lines) or ["(empty log)"]))
