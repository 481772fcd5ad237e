"""User mistakes at every entry point: one line on stderr, exit code 2, and nothing started or left behind.

Each case shows the exit code, the one-line message, and that no process, socket directory, report directory
or partial file is left.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from tests.components import TEST_STAGES

ROOT = Path(__file__).resolve().parents[1]
TMP = Path("/tmp")
EXIT_USAGE = 2


@pytest.fixture
def talk(tmp_path) -> Path:
    path = tmp_path / "talk.wav"
    sf.write(path, (0.3 * np.sin(np.arange(16000) / 16000 * 2 * np.pi * 220)).astype(np.float32), 16000)
    return path


def start_usage_error(cmd: list[str], cwd: Path = ROOT) -> subprocess.Popen:
    """Start an entry point in its own session."""
    return subprocess.Popen(
        cmd,
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )


def finish_usage_error(proc: subprocess.Popen) -> tuple[int, str, int]:
    """Wait for a started entry point; (exit code, stderr, pid)."""
    out, err = proc.communicate(timeout=300)
    assert out == "", out
    return proc.returncode, err, proc.pid


def run_usage_error(cmd: list[str], cwd: Path = ROOT) -> tuple[int, str, int]:
    return finish_usage_error(start_usage_error(cmd, cwd))


def run_usage_errors(cmds: dict[str, list[str]]) -> dict[str, tuple[int, str, int]]:
    """Every command started at once (each spends most of its time importing) -> {name: (exit code, stderr, pid)}."""
    started = {name: start_usage_error(cmd) for name, cmd in cmds.items()}
    return {name: finish_usage_error(proc) for name, proc in started.items()}


def assert_one_line_and_nothing_left(code: int, err: str, pid: int, must_contain: str) -> None:
    assert code == EXIT_USAGE, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and must_contain in lines[0], err
    assert "Traceback" not in err
    assert not list(TMP.glob(f"ecas-{pid}-*")), "a socket directory was created"
    assert not _session_alive(pid), "a process of the run is still alive"


def _session_alive(sid: int) -> list[str]:
    alive = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            alive.append(stat.parent.name)
    return alive


def launch_cmd(*args: str, report: Path) -> list[str]:
    return [sys.executable, str(ROOT / "launch.py"), *args, "--report", str(report)]


# ---- launch.py --------------------------------------------------------------------------------------------------
def test_negative_seed(tmp_path, talk):
    code, err, pid = run_usage_error(launch_cmd("--replay", str(talk), "--seed", "-1", report=tmp_path / "run"))
    assert_one_line_and_nothing_left(code, err, pid, "run.seed: must be >= 0")
    assert not (tmp_path / "run").exists()


def test_empty_config_names_the_missing_checkpoint(tmp_path, talk):
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    code, err, pid = run_usage_error(
        launch_cmd("--replay", str(talk), "--headless", "--config", str(empty), report=tmp_path / "run")
    )
    assert_one_line_and_nothing_left(code, err, pid, "gesture.lm_checkpoint: required")
    assert not (tmp_path / "run").exists()


def test_config_that_is_a_directory(tmp_path, talk):
    code, err, pid = run_usage_error(
        launch_cmd("--replay", str(talk), "--config", f"{tmp_path}/", report=tmp_path / "run")
    )
    assert_one_line_and_nothing_left(code, err, pid, "is a directory, not a YAML config file")


def test_report_at_an_existing_file(tmp_path, talk):
    taken = tmp_path / "report.txt"
    taken.write_text("keep me")
    code, err, pid = run_usage_error(launch_cmd("--replay", str(talk), *TEST_STAGES, report=taken))
    assert_one_line_and_nothing_left(code, err, pid, f"--report {taken}: exists and is not a directory")
    assert taken.read_text() == "keep me"


def test_mp4_that_cannot_be_written(tmp_path, talk):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    code, err, pid = run_usage_error(
        launch_cmd(
            "--replay",
            str(talk),
            "--headless",
            "--mp4",
            str(blocker / "out.mp4"),
            *TEST_STAGES,
            report=tmp_path / "run",
        )
    )
    assert_one_line_and_nothing_left(code, err, pid, f"--mp4 {blocker / 'out.mp4'}: cannot write there")
    assert not (tmp_path / "run").exists()


def test_a_busy_tcp_port_names_the_port_and_the_option(tmp_path, talk):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, err, pid = run_usage_error(
            launch_cmd(
                "--replay",
                str(talk),
                "--headless",
                *TEST_STAGES,
                "--set",
                "bus.transport=tcp",
                "--set",
                f"bus.base_port={port - 2}",
                report=tmp_path / "run",
            )
        )  # port - 2 + 2: gesture's port
    assert_one_line_and_nothing_left(code, err, pid, f"bus.base_port: tcp port {port} on 127.0.0.1 (gesture) is in use")
    assert not (tmp_path / "run").exists()


def test_a_second_dashboard_on_a_busy_port(tmp_path, talk):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, err, pid = run_usage_error(
            launch_cmd("--replay", str(talk), *TEST_STAGES, "--set", f"dashboard.port={port}", report=tmp_path / "run")
        )
    assert_one_line_and_nothing_left(code, err, pid, f"dashboard.port: 127.0.0.1:{port} is in use")
    assert "http://" not in err  # no other run's URL


# ---- render.play --------------------------------------------------------------------------------------------------
T = 50


def _motion(path: Path, **overrides) -> Path:
    arrays = dict(
        poses=np.zeros((T, 165)),
        trans=np.zeros((T, 3)),
        expressions=np.zeros((T, 100)),
        mocap_frame_rate=np.float32(25),
    )
    arrays.update(overrides)
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


def _nan_poses() -> np.ndarray:
    poses = np.zeros((T, 165))
    poses[3, 3] = np.nan
    return poses


def _file(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


PLAY_CASES = {
    "missing npz": (lambda d: d / "missing.npz", [], "no such file"),
    "empty file": (lambda d: _file(d / "empty.npz", b""), [], "the file is empty"),
    "text file": (lambda d: _file(d / "text.npz", b"hello\n"), [], "not an npz archive"),
    "wrong keys": (lambda d: _motion(d / "keys.npz", poses=None, pose=np.zeros((T, 165))), [], "no 'poses' array"),
    "wrong shape": (lambda d: _motion(d / "shape.npz", poses=np.zeros((T, 160))), [], "'poses' must be (T, 165)"),
    "NaN": (lambda d: _motion(d / "nan.npz", poses=_nan_poses()), [], "'poses' contains NaN"),
    "fps 0": (lambda d: _motion(d / "fps.npz", mocap_frame_rate=np.float32(0)), [], "frame rate must be positive"),
    "missing wav": (lambda d: _motion(d / "ok.npz"), ["--wav", "{d}/nope.wav"], "nope.wav: no such file"),
    "non-audio wav": (lambda d: _motion(d / "ok.npz"), ["--wav", "{d}/ok.npz"], "not a readable audio file"),
    "size 0": (lambda d: _motion(d / "ok.npz"), ["--size", "0"], "--size: must be a positive even number"),
}


@pytest.fixture(scope="module")
def play_cases(tmp_path_factory) -> dict[str, tuple[Path, Path]]:
    """A directory per PLAY_CASES case and the motion file made there: {case: (dir, motion)}."""
    made = {}
    for case, (make, _, _) in PLAY_CASES.items():
        folder = tmp_path_factory.mktemp("play")
        made[case] = folder, make(folder)
    return made


@pytest.fixture(scope="module")
def play_results(play_cases) -> dict[str, tuple[int, str, int]]:
    """`render.play` on every case, side by side."""
    return run_usage_errors(
        {
            case: [
                sys.executable,
                "-m",
                "render.play",
                str(motion),
                *[a.format(d=folder) for a in PLAY_CASES[case][1]],
                "--mp4",
                str(folder / "out" / "video.mp4"),
            ]
            for case, (folder, motion) in play_cases.items()
        }
    )


@pytest.mark.parametrize("case", sorted(PLAY_CASES))
def test_render_play_rejects_bad_input_in_one_line(play_cases, play_results, case):
    folder, _ = play_cases[case]
    assert_one_line_and_nothing_left(*play_results[case], PLAY_CASES[case][2])
    assert not (folder / "out" / "video.mp4").exists() and not list(folder.rglob("*.partial"))


# ---- the training and data CLIs -----------------------------------------------------------------------------------
CLI_CASES = {
    "train_codec config dir": (["gesture.codec.train", "--config", "{d}", "--region", "upper"], "is a directory"),
    "train_codec steps 0": (
        ["gesture.codec.train", "--config", "ecas/configs/codec/small.yaml", "--region", "upper", "--steps", "0"],
        "--steps: must be >= 1",
    ),
    "train_lm config dir": (
        ["gesture.lm.train", "--config", "{d}", "--data", "{d}", "--out", "{d}/out"],
        "is a directory",
    ),
    "train_lm no recordings": (
        ["gesture.lm.train", "--config", "ecas/configs/lm/small.yaml", "--data", "{d}", "--out", "{d}/out"],
        "not a directory of npz recordings",
    ),
    "train_lm epochs 0": (
        [
            "gesture.lm.train",
            "--config",
            "ecas/configs/lm/small.yaml",
            "--data",
            "{d}",
            "--out",
            "{d}/out",
            "--epochs",
            "0",
        ],
        "--epochs: must be >= 1",
    ),
    "build missing root": (["gesture.data.build", "--root", "{d}/nope", "--out", "{d}/cache"], "nope"),
    "tokenize missing codecs": (
        ["gesture.lm.tokenize", "--root", "{d}", "--codecs", "{d}/nope", "--out", "{d}/tok"],
        "nope",
    ),
}


@pytest.fixture(scope="module")
def cli_cases(tmp_path_factory) -> dict[str, Path]:
    """An empty directory per CLI_CASES case."""
    return {case: tmp_path_factory.mktemp("cli") for case in CLI_CASES}


@pytest.fixture(scope="module")
def cli_results(cli_cases) -> dict[str, tuple[int, str, int]]:
    """Every CLI_CASES command, side by side."""
    return run_usage_errors(
        {case: [sys.executable, "-m", *[a.format(d=d) for a in CLI_CASES[case][0]]] for case, d in cli_cases.items()}
    )


@pytest.mark.parametrize("case", sorted(CLI_CASES))
def test_training_and_data_clis_reject_bad_arguments_in_one_line(cli_cases, cli_results, case):
    assert_one_line_and_nothing_left(*cli_results[case], CLI_CASES[case][1])
    assert not (cli_cases[case] / "out").exists() and not (cli_cases[case] / "tok").exists()
