"""The entry point of every stage process: environment, signals, log file, component, runner."""

from __future__ import annotations

import ctypes
import importlib
import logging
import multiprocessing as mp
import os
import shutil
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import zmq

from agent.sections import AppConfig
from agent.stage import StageRunner, Topology
from ecas.core.bus import bus_addresses
from ecas.core.component import RunContext
from ecas.core.threads import limit_threads

COMPONENT_FACTORIES = {
    "io": "agent.io.process:create_component",
    "dialogue": "dialogue.process:create_component",
    "gesture": "gesture.process:create_component",
    "render": "render.process:create_component",
}
EXIT_STARTUP_FAILED = 3
EXIT_FLUSH_S = 0.3  # at most this long for ZeroMQ to deliver a stopped stage's last messages
PR_SET_PDEATHSIG = 1
SUPERVISOR_DIED = signal.SIGUSR1  # PR_SET_PDEATHSIG's signal; unlike SIGTERM, nothing else sends it


@dataclass(frozen=True)
class StageLaunch:
    """Everything a stage process needs; picklable for multiprocessing spawn."""

    stage: str
    pipeline: tuple[str, ...]
    app: AppConfig
    run: RunContext
    ipc_dir: Path
    factory: str  # "module:function" taking (section config, RunContext)

    @property
    def log_path(self) -> Path:
        return self.run.run_dir / f"{self.stage}.log"


def load_factory(path: str) -> Callable[..., Any]:
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


def stage_main(launch: StageLaunch) -> None:
    """Run one stage until STOP, SIGTERM, the supervisor's death or the end of the stream."""
    supervisor = SupervisorWatch(launch.ipc_dir)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group; the supervisor decides
    redirect_output(launch.log_path)
    logging.basicConfig(
        level=logging.INFO, stream=sys.stderr, format=f"%(asctime)s {launch.stage} %(levelname)s %(name)s: %(message)s"
    )
    limit_threads()
    log = logging.getLogger(launch.stage)
    try:
        section = getattr(launch.app, launch.stage)
        run = replace(launch.run, addresses=bus_addresses(launch.app.bus, launch.ipc_dir))
        component, source = _split(load_factory(launch.factory)(section, run))
        limit_threads()
        topology = Topology.of(launch.stage, launch.pipeline, speaker=launch.app.io.speaker)
        runner = StageRunner(topology, launch.app, launch.run, launch.ipc_dir, component, source)
    except Exception:
        log.exception("failed to start")
        sys.exit(EXIT_STARTUP_FAILED)
    supervisor.stop = runner.request_stop
    signal.signal(signal.SIGTERM, lambda *_: runner.request_stop())
    runner.run()
    log.info("stopped")
    exit_now(0)


def exit_now(code: int) -> None:
    """End a stage process whose work is done, without the interpreter's teardown.

    By now the component has closed (its files are written and renamed into place) and the runner's sockets are
    closed. Left to do: flush the log, and let ZeroMQ deliver the last heartbeat (the stage's final counters) to
    the supervisor, which reads it at once; messages queued for a stage that has stopped reading would hold the
    context for the publisher's whole linger, so that wait is bounded by `EXIT_FLUSH_S`. The interpreter's own
    teardown (finalizers and garbage collection of a heap holding torch and the models, 0.2-1 s on a loaded
    2-core machine) frees nothing the kernel would not, and it sat between Ctrl-C and the last process gone.
    """
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    flushing = threading.Thread(target=zmq.Context.instance().term, name="zmq-term", daemon=True)
    flushing.start()
    flushing.join(EXIT_FLUSH_S)
    os._exit(code)


class SupervisorWatch:
    """Linux: act on the supervisor's death, even by SIGKILL, so no process of the run outlives it or its sockets.

    The kernel sends PR_SET_PDEATHSIG's signal when the supervisor's main thread (which started this process)
    exits; its other threads (ZeroMQ's) may still be alive then, and getppid() names the supervisor until they are
    gone, so only the signal says that it died. The signal is one of its own: a SIGTERM may come from a
    supervisor that lives on. On it the run's private socket directory is removed, then `stop` ends the
    process's work, or the process exits at once while it is still starting (`stop` unset). Each process of the
    run removes the directory after it last created a socket in it, so none is left whatever order they end in.
    """

    def __init__(self, ipc_dir: Path):
        self.ipc_dir = ipc_dir
        self.stop: Callable[[], None] | None = None
        signal.signal(SUPERVISOR_DIED, self._died)
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, SUPERVISOR_DIED)
        except OSError:
            pass
        if os.getppid() != mp.parent_process().pid:  # it died before the request
            self._died()

    def _died(self, *_) -> None:
        remove_ipc_dir(self.ipc_dir)
        if self.stop is None:
            os._exit(EXIT_STARTUP_FAILED)
        self.stop()


def remove_ipc_dir(ipc_dir: Path) -> None:
    """Only a private `ecas-*` directory is removed, never a shared one such as a worker's temp directory.

    Several processes may remove it at once: what one finds gone is another's doing.
    """
    if Path(ipc_dir).name.startswith("ecas-"):
        shutil.rmtree(ipc_dir, ignore_errors=True)


def _split(made: Any) -> tuple[Any, Any]:
    """A factory returns a component, or (component, source) for the io stage."""
    return made if isinstance(made, tuple) else (made, None)


def redirect_output(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    sys.stdout = open(1, "w", buffering=1, closefd=False)
    sys.stderr = open(2, "w", buffering=1, closefd=False)
