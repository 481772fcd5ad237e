"""The entry point of every stage process: environment, signals, log file, component, runner."""

from __future__ import annotations

import ctypes
import importlib
import logging
import os
import shutil
import signal
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

from agent.sections import AppConfig
from agent.stage import StageRunner, Topology
from core.bus import bus_addresses
from core.component import RunContext
from core.threads import limit_threads

COMPONENT_FACTORIES = {
    "io": "agent.io.process:create_component",
    "dialogue": "dialogue.process:create_component",
    "gesture": "gesture.process:create_component",
    "render": "render.process:create_component",
}
EXIT_STARTUP_FAILED = 3
PR_SET_PDEATHSIG = 1


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
    """Run one stage until STOP, SIGTERM or the end of the stream."""
    die_with_parent()
    supervisor_pid = os.getppid()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group; the supervisor decides
    redirect_output(launch.log_path)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s {launch.stage} %(levelname)s %(name)s: %(message)s")
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
    signal.signal(signal.SIGTERM, lambda *_: runner.request_stop())
    try:
        runner.run()
    finally:
        remove_ipc_dir_if_orphaned(launch.ipc_dir, supervisor_pid)
    log.info("stopped")


def remove_ipc_dir_if_orphaned(ipc_dir: Path, supervisor_pid: int) -> None:
    """The supervisor was killed (it cannot clean up): the run's private socket directory goes with its stages.

    Only a private `ecas-*` directory is removed, never a shared one such as a worker's temp directory.
    """
    if os.getppid() != supervisor_pid and Path(ipc_dir).name.startswith("ecas-"):
        shutil.rmtree(ipc_dir, ignore_errors=True)


def _split(made: Any) -> tuple[Any, Any]:
    """A factory returns a component, or (component, source) for the io stage."""
    return made if isinstance(made, tuple) else (made, None)


def die_with_parent() -> None:
    """Linux: get SIGTERM when the supervisor dies, so no stage is ever orphaned."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def redirect_output(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    sys.stdout = open(1, "w", buffering=1, closefd=False)
    sys.stderr = open(2, "w", buffering=1, closefd=False)
