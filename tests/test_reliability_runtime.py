"""Failures while the run is going: a sink that cannot write, a stage that stalls, kills, and busy-waiting.

Each case shows the exit code, the one-line message, and that no process, socket directory or partial file is
left. The components below are for these tests only (factories named by `run.components`).
"""

from __future__ import annotations

import json
import os
import re
import resource
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
import yaml

from agent.sections import RunConfig
from agent.supervisor import remove_dead_runs_ipc_dirs
from ecas.core.messages import DialogueStep, Message
from tests import components
from tests.test_runtime import finish, leftovers
from tests.test_runtime import launch as launch_with_test_stages

ROOT = Path(__file__).resolve().parents[1]
TMP = Path("/tmp")
STALL_AT_STEP = "TEST_STALL_AT_STEP"
REAL_RENDER = ["--set", "run.components.render=render.process:create_component", "--set", "render.size=64"]
MP4_SIZE_LIMIT_BYTES = 80_000  # above every report file (latency.png is 47-60 kB), below the MP4 (126 kB for 12 s)


# ---- components -------------------------------------------------------------------------------------------------
class StallingGesture(components.WaveGesture):
    """Answers every step until `TEST_STALL_AT_STEP`, then takes its input and publishes nothing."""

    def handle(self, msg: Message) -> Sequence[Message]:
        if isinstance(msg, DialogueStep) and msg.step >= int(os.environ[STALL_AT_STEP]):
            return ()
        return super().handle(msg)


def stalling_gesture(cfg, run) -> StallingGesture:
    return StallingGesture()


# ---- helpers ----------------------------------------------------------------------------------------------------
def launch(args: list[str], report: Path, env: dict | None = None, **kw) -> subprocess.Popen:
    """launch.py with the test stages, then `args` (so a component or option given here wins)."""
    return launch_with_test_stages(["--set", "dashboard.enabled=false", *args], report, env, **kw)


def recording(path: Path, seconds: float) -> Path:
    t = np.arange(int(seconds * 16000)) / 16000
    sf.write(path, (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), 16000)
    return path


def ipc_dirs(pid: int) -> list[Path]:
    return list(TMP.glob(f"ecas-{pid}-*"))


def wait_until(predicate, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"{what}: not reached in {timeout_s} s"
        time.sleep(0.05)


def error_line(output: str) -> str:
    """The supervisor's one-line verdict."""
    lines = [line for line in output.splitlines() if " supervisor ERROR: " in line]
    assert len(lines) == 1, output
    return lines[0].split(" supervisor ERROR: ", 1)[1]


def stage_pid(launcher_pid: int, stage: str) -> int | None:
    """The child of the launcher whose stdout is the stage's log."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            if parent == launcher_pid and os.readlink(entry / "fd" / "1").endswith(f"/{stage}.log"):
                return int(entry.name)
        except (OSError, IndexError, ValueError):
            continue
    return None


def spawned(launcher_pid: int) -> int:
    """How many children of the launcher run multiprocessing's spawn (its stages), from their very start."""
    count = 0
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            count += parent == launcher_pid and b"spawn_main" in (entry / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
    return count


def limit_file_size() -> None:
    """Every file of the run may grow to MP4_SIZE_LIMIT_BYTES: what a disk that fills does to the MP4.

    Python ignores SIGXFSZ, so a write beyond the limit fails with EFBIG ("File too large").
    """
    resource.setrlimit(resource.RLIMIT_FSIZE, (MP4_SIZE_LIMIT_BYTES, MP4_SIZE_LIMIT_BYTES))


# ---- a sink that cannot write ---------------------------------------------------------------------------------
def test_a_sink_that_cannot_write_stops_the_run_in_one_line(tmp_path):
    wav = recording(tmp_path / "talk.wav", 12.0)
    mp4 = tmp_path / "out" / "talk.mp4"
    proc = launch(
        ["--replay", str(wav), "--headless", "--mp4", str(mp4), *REAL_RENDER],
        tmp_path / "run",
        preexec_fn=limit_file_size,
    )
    code, output = finish(proc, timeout_s=300)
    assert code == 1, output
    line = error_line(output)
    assert line == f"stage 'render' failed: cannot write {mp4} ([Errno 27] File too large)", output
    assert not mp4.exists() and not list(mp4.parent.glob("*.partial"))
    assert leftovers(proc.pid) == [] and ipc_dirs(proc.pid) == []


def test_a_stage_that_makes_no_progress_while_its_input_waits_fails_the_run(tmp_path):
    wav = recording(tmp_path / "talk.wav", 3.0)
    proc = launch(
        [
            "--replay",
            str(wav),
            "--fast",
            "--set",
            "run.components.gesture=tests.test_reliability_runtime:stalling_gesture",
            "--set",
            "bus.stall_timeout_s=2",
        ],
        tmp_path / "run",
        {STALL_AT_STEP: "5"},
    )
    code, output = finish(proc)
    assert code == 1, output
    line = error_line(output)
    assert re.fullmatch(
        r"stage 'gesture' made no progress for [2-9] s while its input waited \(it got to "
        r"step 4, 'dialogue' to step \d+; bus.stall_timeout_s=2\); see .*gesture.log",
        line,
    ), line
    assert leftovers(proc.pid) == [] and ipc_dirs(proc.pid) == []


# ---- kills ------------------------------------------------------------------------------------------------------
def test_a_render_stage_killed_while_writing_leaves_no_partial_mp4(tmp_path):
    wav = recording(tmp_path / "talk.wav", 60.0)
    mp4 = tmp_path / "out" / "talk.mp4"
    proc = launch(["--replay", str(wav), "--headless", "--mp4", str(mp4), *REAL_RENDER], tmp_path / "run")
    wait_until(
        lambda: any(p.stat().st_size > 0 for p in mp4.parent.glob("*.partial")) or proc.poll() is not None,
        120,
        "the render stage writes its MP4",
    )
    render = stage_pid(proc.pid, "render")
    assert render is not None and proc.poll() is None
    os.kill(render, signal.SIGKILL)
    code, output = finish(proc)
    assert code == 1, output
    assert "stage 'render' died (exit code -9)" in output
    assert not mp4.exists() and not list(mp4.parent.glob("*.partial")), list(mp4.parent.iterdir())
    assert leftovers(proc.pid) == [] and ipc_dirs(proc.pid) == []


@pytest.mark.parametrize("when", ["starting", "running"])
def test_a_killed_launcher_leaves_no_socket_directory(tmp_path, when):
    """Killed while its stages start or once they run: whatever order they end in, they leave no directory."""
    wav = recording(tmp_path / "talk.wav", 60.0)
    proc = launch(["--replay", str(wav), "--set", "dashboard.enabled=false"], tmp_path / "run")
    if when == "starting":
        wait_until(lambda: spawned(proc.pid) == 4, 120, "the four stages are started")
    else:
        wait_until(lambda: "ready" in _read(tmp_path / "run" / "render.log"), 120, "the stages are ready")
    assert ipc_dirs(proc.pid)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=30)
    assert leftovers(proc.pid) == []  # the stages follow their supervisor
    wait_until(lambda: not ipc_dirs(proc.pid), 10, "the stages remove the socket directory")


def test_the_next_run_removes_socket_directories_of_dead_runs_only(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    dead_dir, live_dir, other = (
        tmp_path / f"ecas-{dead.pid}-abc",
        tmp_path / f"ecas-{os.getpid()}-def",
        tmp_path / "ecas-notapid",
    )
    for d in (dead_dir, live_dir, other):
        d.mkdir()
        (d / "io.sock").write_text("")
    assert remove_dead_runs_ipc_dirs(tmp_path) == [dead_dir]
    assert not dead_dir.exists() and live_dir.exists() and other.exists()


# ---- report directories -----------------------------------------------------------------------------------------
def test_runs_started_in_the_same_second_get_their_own_report_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    made: list[Path] = []
    threads = [
        threading.Thread(target=lambda: made.append(RunConfig().make_report_dir("20260101-000000"))) for _ in range(16)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(made)) == 16 and all(p.is_dir() and p.name.startswith("20260101-000000-") for p in made)


# ---- no busy-waiting ---------------------------------------------------------------------------------------------
def test_an_offline_source_waiting_for_credit_does_not_spin(tmp_path):
    """The renderer takes 80 ms a step; the io stage waits for credit nearly all the run and must sleep."""
    wav = recording(tmp_path / "talk.wav", 8.0)
    env = {components.RENDER_SLEEP_S: "0.08"}  # per gesture step: real time
    code, output = finish(
        launch(["--replay", str(wav), "--fast", "--set", "bus.credit_window_steps=4"], tmp_path / "run", env)
    )
    assert code == 0, output
    latency = json.loads((tmp_path / "run" / "latency.json").read_text())
    wall_s = latency["stream"]["stream_wall_s"]
    io_cpu_s = latency["counters"]["io"]["cpu_s"]  # includes its start-up (imports)
    assert wall_s > 6.0, "the renderer paced the run"
    assert io_cpu_s < 0.3 * wall_s, f"io used {io_cpu_s} s of CPU in a {wall_s} s stream"
    # the offline table reports throughput and compute, and no end-to-end "latency"
    assert "x real time" in output and "frames/s" in output and "compute p50 ms" in output
    assert "end to end" not in output
    assert latency["mode"] == "offline" and latency["throughput"]["realtime_factor"] > 0


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


# ---- tcp ----------------------------------------------------------------------------------------------------------
def bus_ports(report: Path) -> set[int]:
    """The tcp ports a run bound, from the config it wrote."""
    endpoints = yaml.safe_load((report / "config.yaml").read_text())["bus"]["endpoints"]
    assert set(endpoints) >= {"io", "dialogue", "gesture", "render", "supervisor"}
    return {int(address.rsplit(":", 1)[1]) for address in endpoints.values()}


def test_two_tcp_runs_on_one_host_take_free_ports_and_both_finish(tmp_path):
    wav = recording(tmp_path / "talk.wav", 1.0)
    tcp = ["--replay", str(wav), "--fast", "--set", "bus.transport=tcp", "--set", "bus.base_port=0"]
    first, second = launch(tcp, tmp_path / "first"), launch(tcp, tmp_path / "second")
    for proc in (first, second):
        code, output = finish(proc)
        assert code == 0, output
        assert leftovers(proc.pid) == [] and ipc_dirs(proc.pid) == []
    assert not bus_ports(tmp_path / "first") & bus_ports(tmp_path / "second")
