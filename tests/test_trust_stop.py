"""Issue 46, Ctrl-C: SIGINT to a run's process group ends every process with exit code 130 and a complete report.

`bus.stop_timeout_s` is set far beyond the tests' deadlines, so a run that exits within them stopped by itself:
each process heard STOP, wrote its files and exited, and none had to be terminated. How long the stop takes on a
loaded machine is measured by `python -m bench.stop` (docs/reliability.md), not asserted here.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ecas.core.bus import BusConfig
from ecas.core.config import ConfigError
from tests.test_reliability_runtime import ipc_dirs, recording, wait_until
from tests.test_runtime import ROOT, finish, launch, leftovers

PATIENT_STOP = ["--set", "bus.stop_timeout_s=3600"]  # the supervisor would wait an hour before any SIGTERM
STOP_DEADLINE_S = 60  # the test's patience, far below that hour
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
PNG_END = b"IEND\xaeB`\x82"


def loading_forever(cfg, run):
    """A stage whose models never finish loading: it never runs its loop, so it cannot hear STOP."""
    time.sleep(3600)


def interrupt(proc: subprocess.Popen) -> tuple[int, str]:
    """Ctrl-C: SIGINT to the whole foreground group; wait for the launcher's exit."""
    os.killpg(proc.pid, signal.SIGINT)
    try:
        return finish(proc, STOP_DEADLINE_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # leave nothing running behind a failed test
        raise


def assert_whole_png(path: Path) -> None:
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC) and data.endswith(PNG_END), f"{path} is not a whole PNG"


@pytest.mark.parametrize("option", ["stop_timeout_s", "ready_timeout_s"])
def test_a_stop_or_ready_timeout_must_be_positive(option):
    with pytest.raises(ConfigError, match=rf"bus.{option}: must be > 0, got -1"):
        BusConfig(**{option: -1.0})


def test_ctrl_c_on_a_live_run_stops_every_process_by_itself_with_a_whole_report(tmp_path):
    wav = recording(tmp_path / "long.wav", 30)
    report = tmp_path / "run"
    proc = launch(["--replay", str(wav), *PATIENT_STOP], report)  # live, with the dashboard
    wait_until(lambda: received_steps(report) >= 5, 120, "five steps at the sink")
    code, output = interrupt(proc)
    assert code == 130, output
    latency = json.loads((report / "latency.json").read_text())
    assert latency["steps_measured"] >= 5
    assert_whole_png(report / "latency.png")
    for name in ("io", "dialogue", "gesture", "render", "dashboard"):
        assert _read(report / f"{name}.log").rstrip().endswith("stopped"), f"{name} did not stop by itself"
    assert leftovers(proc.pid) == []
    assert ipc_dirs(proc.pid) == []


def test_ctrl_c_during_the_start_up_does_not_wait_for_a_stage_still_loading(tmp_path):
    wav = recording(tmp_path / "talk.wav", 5)
    report = tmp_path / "run"
    gesture = ["--set", "run.components.gesture=tests.test_trust_stop:loading_forever"]
    proc = launch(["--replay", str(wav), "--set", "dashboard.enabled=false", *gesture, *PATIENT_STOP], report)
    wait_until(lambda: "ready" in _read(report / "dialogue.log"), 120, "the dialogue stage ready")
    code, output = interrupt(proc)
    assert code == 130, output
    assert _read(report / "dialogue.log").rstrip().endswith("stopped")
    assert leftovers(proc.pid) == []
    assert ipc_dirs(proc.pid) == []


def test_sigterm_to_the_whole_group_during_the_start_up_is_a_stop_not_a_failure(tmp_path):
    """`kill -TERM -- -PGID` (or a service manager) reaches every process at once: a stage or the dashboard that
    ends of it before the supervisor has acted is part of the stop, not a failure (it was "the dashboard died")."""
    wav = recording(tmp_path / "talk.wav", 5)
    report = tmp_path / "run"
    gesture = ["--set", "run.components.gesture=tests.test_trust_stop:loading_forever"]  # the run never starts
    proc = launch(["--replay", str(wav), *gesture, *PATIENT_STOP], report)  # with the dashboard
    wait_until(lambda: "ready" in _read(report / "dialogue.log"), 120, "the dialogue stage ready")
    os.killpg(proc.pid, signal.SIGTERM)
    code, output = finish(proc, STOP_DEADLINE_S)
    assert code == 130, output
    assert " ERROR" not in output, output
    assert leftovers(proc.pid) == []
    assert ipc_dirs(proc.pid) == []


def test_ctrl_c_on_the_shipped_agent_offline_leaves_its_motion_and_no_partial_mp4(tmp_path):
    """The real stages (default config) on the bundled recording, offline with an MP4, stopped mid-stream."""
    report = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "launch.py"), "--headless", "--mp4", str(tmp_path / "out.mp4")]
    proc = subprocess.Popen(
        [*cmd, "--report", str(report), *PATIENT_STOP],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    wait_until(lambda: "ready" in _read(report / "render.log") or proc.poll() is not None, 300, "the stages ready")
    time.sleep(3.0)  # a few seconds of motion
    code, output = interrupt(proc)
    assert code == 130, output
    with np.load(report / "motion.npz", allow_pickle=False) as motion:
        assert motion["poses"].shape[0] > 0 and np.isfinite(motion["poses"]).all()
    json.loads((report / "latency.json").read_text())
    json.loads((report / "transcript.json").read_text())
    assert not (tmp_path / "out.mp4").exists()  # an offline run stopped before its end leaves no MP4
    assert [p for p in tmp_path.iterdir() if p.name.startswith(".out.mp4")] == []
    assert leftovers(proc.pid) == []
    assert ipc_dirs(proc.pid) == []


def received_steps(report: Path) -> int:
    """Gesture steps the test sink has recorded so far."""
    return _read(report / "received.jsonl").count('"gesture.step"')


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""
