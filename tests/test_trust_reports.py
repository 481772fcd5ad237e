"""Issue 46, cases 3, 4 and 9 (the report folder): a report directory belongs to one run, a report file is whole
or absent (never truncated), and a folder that cannot be created or written is one line and exit 2."""

from __future__ import annotations

import json
import resource
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from agent.report_lock import LOCK_FILE, ReportLock
from dialogue.transcript import Transcript, Turn
from ecas.core.atomic import write_text_atomic
from ecas.core.config import ConfigError
from ecas.core.messages import N_GESTURE_TOKENS, GestureStep
from gesture.motion_spool import MotionSpool
from gesture.process import MOTION_FPS, write_motion
from tests.test_reliability_runtime import ipc_dirs, launch, recording
from tests.test_reliability_usage import assert_one_line_and_nothing_left, launch_cmd, run_usage_error
from tests.test_runtime import finish, leftovers


class FileSizeLimit:
    """Files this process writes may grow to `limit_bytes` (what a full disk does to a write: EFBIG, not a crash;
    Python ignores SIGXFSZ)."""

    def __init__(self, limit_bytes: int):
        self.limit = limit_bytes

    def __enter__(self):
        self.previous = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (self.limit, self.previous[1]))

    def __exit__(self, *exc):
        resource.setrlimit(resource.RLIMIT_FSIZE, self.previous)


def no_temporary_files(directory: Path) -> bool:
    return not [p for p in directory.iterdir() if p.name.endswith((".tmp", ".partial"))]


def steps(n: int) -> list[GestureStep]:
    rng = np.random.default_rng(0)
    return [
        GestureStep(
            step=i,
            poses=rng.normal(size=(2, 55, 3)).astype(np.float32),
            trans=np.zeros((2, 3), np.float32),
            expressions=np.zeros((2, 100), np.float32),
            tokens=np.zeros(N_GESTURE_TOKENS, np.int32),
            va_prob=0.5,
        )
        for i in range(n)
    ]


def test_a_failed_write_leaves_the_previous_report_file_whole(tmp_path):
    """motion.npz, transcript.json, latency.json (any text report): a write that fails past the size limit."""
    motion, transcript, text = tmp_path / "motion.npz", tmp_path / "transcript.json", tmp_path / "latency.json"
    write_motion(motion, steps(2))
    talk = Transcript("local")
    talk.add(Turn("user", 0.0, 1.0, text="hello"))
    talk.write(transcript)
    write_text_atomic(text, '{"ok": true}')
    before = {p: p.read_bytes() for p in (motion, transcript, text)}
    for turn in range(2000):
        talk.add(Turn("agent", turn, turn + 1.0, text="a long answer " * 5))
    with FileSizeLimit(4096):
        with pytest.raises(OSError, match="File too large"):
            write_motion(motion, steps(400))
        with pytest.raises(OSError, match="File too large"):
            talk.write(transcript)
        with pytest.raises(OSError, match="File too large"):
            write_text_atomic(text, "x" * 10_000)
    assert {p: p.read_bytes() for p in before} == before
    assert no_temporary_files(tmp_path), list(tmp_path.iterdir())
    with np.load(motion) as data:
        assert data["poses"].shape == (4, 165)


def test_a_second_run_with_the_same_report_gets_one_line(tmp_path):
    """Case 3: the second run is refused in one line with exit 2 while the first one runs on and finishes."""
    report = tmp_path / "run"
    first = launch(["--replay", str(recording(tmp_path / "long.wav", 6.0))], report)
    deadline = time.monotonic() + 120
    while not (report / "config.yaml").exists():
        assert first.poll() is None and time.monotonic() < deadline, "the first run never started"
        time.sleep(0.05)
    code, err, pid = run_usage_error(launch_cmd("--replay", str(tmp_path / "long.wav"), report=report))
    assert_one_line_and_nothing_left(code, err, pid, f"another run (pid {first.pid}) is writing its report there")
    assert ipc_dirs(pid) == []
    code, output = finish(first, timeout_s=300)
    assert code == 0, output
    assert json.loads((report / "latency.json").read_text())
    assert not (report / LOCK_FILE).exists() and no_temporary_files(report)
    assert leftovers(first.pid) == []


def test_the_lock_is_released_when_its_holder_dies(tmp_path):
    ReportLock(tmp_path).acquire()  # never released: this test's process holds it
    with pytest.raises(ConfigError, match=r"--report .*another run \(pid \d+\)"):
        ReportLock(tmp_path).acquire()  # another open file description: refused as another process would be


def test_a_report_folder_that_cannot_be_created(tmp_path, talk):
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, err, pid = run_usage_error(launch_cmd("--replay", str(talk), report=blocker / "run"))
    assert_one_line_and_nothing_left(code, err, pid, f"--report {blocker / 'run'}: cannot create it")


def test_a_full_disk_before_the_run_leaves_no_empty_config(tmp_path, talk):
    """Case 4 at (almost) 0 bytes free: one line, exit 2, and the report folder it made is gone (no empty
    config.yaml). 1 kB, not 0: Python's tempfile needs a few bytes to find a usable temporary directory."""
    report = tmp_path / "run"
    cmd = launch_cmd("--replay", str(talk), "--headless", report=report)
    proc = subprocess.Popen(
        cmd,
        cwd=Path(__file__).resolve().parents[1],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (1000, resource.RLIM_INFINITY)),
    )
    out, err = proc.communicate(timeout=300)
    assert out == ""
    assert_one_line_and_nothing_left(proc.returncode, err, proc.pid, f"--report {report}: cannot write there")
    assert not report.exists()


@pytest.fixture
def talk(tmp_path) -> Path:
    return recording(tmp_path / "talk.wav", 1.0)


@pytest.mark.parametrize("chunk_steps", [5, 4096])  # 37 steps: 7 whole chunks and 2 steps, or one chunk
def test_the_spooled_motion_record_equals_the_whole_one(tmp_path, monkeypatch, chunk_steps):
    """The gesture stage's offline record goes to disk step by step (flat memory); motion.npz is the same file."""
    monkeypatch.setattr("gesture.motion_spool.CHUNK_STEPS", chunk_steps)
    recorded = steps(37)
    for step in recorded:
        step.tokens = np.arange(N_GESTURE_TOKENS, dtype=np.int32) * 1000 + step.step
    write_motion(tmp_path / "whole.npz", recorded)
    spool = MotionSpool(tmp_path / "motion.npz")
    for step in recorded:
        spool.append(step)
    assert spool.partial_files() == [spool.spool_path] and spool.spool_path.exists()
    spool.close(MOTION_FPS)
    assert spool.partial_files() == [] and not spool.spool_path.exists()
    with np.load(tmp_path / "whole.npz") as whole, np.load(tmp_path / "motion.npz") as spooled:
        assert sorted(whole.files) == sorted(spooled.files)
        for key in whole.files:
            assert whole[key].dtype == spooled[key].dtype, key
            np.testing.assert_array_equal(whole[key], spooled[key], err_msg=key)


def test_a_disk_that_fills_during_the_run_leaves_the_previous_reports(tmp_path):
    """Case 4 during a run: the second run on a report folder cannot write all of its report (the size limit lies
    between the first run's latency.json and its latency.png); every report file is the first run's or a whole new
    one, never truncated, and no temporary file is left."""
    report, talk = tmp_path / "run", recording(tmp_path / "talk.wav", 1.0)
    code, output = finish(launch(["--replay", str(talk), "--fast"], report))
    assert code == 0, output
    first = {name: (report / name).read_bytes() for name in ("latency.json", "latency.png")}
    limit = len(first["latency.png"]) // 2

    def small_disk() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))

    code, output = finish(launch(["--replay", str(talk), "--fast"], report, preexec_fn=small_disk))
    assert code == 1 and "error: cannot write the latency report" in output, output
    assert (report / "latency.png").read_bytes() == first["latency.png"]  # the one that failed: the previous file
    assert json.loads((report / "latency.json").read_text())  # written whole (it fits)
    assert no_temporary_files(report) and not (report / LOCK_FILE).exists()
