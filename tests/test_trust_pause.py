"""Issue 46, case 7: a pause of the whole run (Ctrl-Z then fg, SIGSTOP/SIGCONT of its process group, a laptop's
suspend) is not a stage failure; one stopped stage still is, and is named."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from tests.test_reliability_runtime import error_line, ipc_dirs, launch, recording, stage_pid, wait_until
from tests.test_runtime import finish, leftovers

HEARTBEAT_TIMEOUT_S = 3.0
PAUSE_S = 2.5 * HEARTBEAT_TIMEOUT_S
FAST_HEARTBEATS = ["--set", f"bus.heartbeat_timeout_s={HEARTBEAT_TIMEOUT_S:g}"]


def start_live_run(tmp_path: Path, seconds: float):
    report = tmp_path / "run"
    proc = launch(["--replay", str(recording(tmp_path / "talk.wav", seconds)), *FAST_HEARTBEATS], report)
    wait_until(lambda: all(stage_pid(proc.pid, s) for s in ("io", "dialogue", "gesture", "render")), 120, "stages")
    return proc, report


def test_a_paused_run_resumes_and_finishes(tmp_path):
    proc, report = start_live_run(tmp_path, 20.0)
    time.sleep(3 * 0.25)  # a few heartbeats: the stages are past "starting"
    os.killpg(proc.pid, signal.SIGSTOP)  # the launcher and every stage, as Ctrl-Z does
    time.sleep(PAUSE_S)
    os.killpg(proc.pid, signal.SIGCONT)
    code, output = finish(proc, timeout_s=300)
    assert code == 0, output
    assert "stopped responding" not in output
    assert "the supervisor was paused for" in output, output
    assert leftovers(proc.pid) == [] and ipc_dirs(proc.pid) == []


def test_one_stopped_stage_is_named(tmp_path):
    proc, report = start_live_run(tmp_path, 30.0)
    gesture = stage_pid(proc.pid, "gesture")
    time.sleep(3 * 0.25)
    os.kill(gesture, signal.SIGSTOP)
    try:
        code, output = finish(proc, timeout_s=300)
    finally:
        try:
            os.kill(gesture, signal.SIGCONT)
        except ProcessLookupError:
            pass
    assert code == 1, output
    assert error_line(output).startswith("stage 'gesture' stopped responding (no heartbeat for "), output
    assert leftovers(proc.pid) == [] and ipc_dirs(proc.pid) == []
