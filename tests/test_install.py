"""The installed package runs from another directory: a wheel built from this checkout holds every file a module
reads from beside itself, and installed into a new virtual environment it answers `ecas --help` and speaks the
packaged example from a working directory that is not the checkout.

The new environment reuses this one's third-party packages (a `.pth` line naming its site-packages, whose own `.pth`
files, such as an editable install's, are then not run) and gets the wheel with `--no-deps`: the project's own
modules come only from the wheel. `pip install <checkout>` into a truly fresh environment, which also resolves the
requirements, takes minutes and is timed in docs/install.md.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import numpy as np
import pytest

from ecas.cli import COMMANDS

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("ecas", "agent", "dialogue", "gesture", "render", "bench")
SOURCE_TOP_SKIP = {"build", "runs", "out", "cache", "data", "tests", "docs", "scripts"}


def _source_skip(directory: str, names: list[str]) -> set[str]:
    """What the copy of the checkout leaves out: caches and hidden files anywhere, work folders at the top."""
    top = Path(directory) == REPO
    hidden = {n for n in names if n.startswith(".") or n == "__pycache__" or n.endswith(".egg-info")}
    return hidden | ({n for n in names if n in SOURCE_TOP_SKIP} if top else set())


# files read from beside a module, by the modules that read them
PACKAGE_DATA = (
    "ecas/configs/default.yaml",  # ecas.core.paths
    "ecas/configs/miburi-release.yaml",
    "ecas/configs/lm/small.yaml",
    "ecas/configs/codec/default_small.yaml",
    "ecas/configs/data/clip.yaml",
    "ecas/checkpoints/gesture_lm/lm.safetensors",
    "ecas/checkpoints/gesture_lm/lm.json",
    "ecas/checkpoints/gesture_lm/speakers.json",
    "ecas/checkpoints/codecs/upper/model.safetensors",
    "ecas/checkpoints/codecs/lower/config.yaml",
    "ecas/checkpoints/codecs/face/model.safetensors",
    "ecas/checkpoints/speech_tokenizer/speech_tokenizer.safetensors",
    "ecas/examples/librivox_0870.wav",
    "ecas/examples/librivox_0870.txt",
    "agent/dashboard/static/index.html",  # agent.dashboard.server
    "render/shaders/mesh.vert",  # render.renderer
    "gesture/synth/calibration.json",  # gesture.synth.calibration
)


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout_s: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout_s)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built from a copy of the checkout (the build leaves nothing in the checkout itself)."""
    root = tmp_path_factory.mktemp("wheel")
    source = root / "source"
    shutil.copytree(REPO, source, ignore=_source_skip, symlinks=False)
    build = _run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(root), str(source)],
        root,
        {**os.environ, "PIP_NO_INDEX": "1"},
    )
    assert build.returncode == 0, build.stderr
    (path,) = root.glob("embodied_agent-*.whl")
    return path


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """(bin directory, environment) of a new venv holding the wheel, with this environment's third-party packages."""
    venv = tmp_path_factory.mktemp("venv") / "env"
    made = _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], venv.parent, dict(os.environ))
    assert made.returncode == 0, made.stderr
    site = Path(
        _run(
            [str(venv / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            venv.parent,
            dict(os.environ),
        ).stdout.strip()
    )
    (site / "shared_site_packages.pth").write_text(sysconfig.get_path("purelib") + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    pip = [sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "-q"]
    install = _run([*pip, "--no-deps", "--no-index", str(wheel)], venv.parent, env)
    assert install.returncode == 0, install.stderr
    return venv / "bin", env


def test_the_wheel_holds_the_package_data_and_no_tests(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = [name for name in PACKAGE_DATA if name not in names]
    assert not missing, f"not in the wheel: {missing}"
    tops = {name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")}
    assert tops == set(PACKAGES)
    shipped = {
        str(p.relative_to(REPO))
        for p in (REPO / "ecas" / "checkpoints").rglob("*")
        if p.is_file() and p.suffix != ".pyc"
    }
    assert shipped <= names  # every shipped checkpoint file, model cards included
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "ecas = ecas.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()


def test_ecas_help_from_another_directory(installed, tmp_path):
    bin_dir, env = installed
    where = _run(
        [str(bin_dir / "python"), "-c", "import ecas, gesture; print(ecas.__file__, gesture.__file__)"], tmp_path, env
    )
    assert where.returncode == 0, where.stderr
    assert all(Path(p).is_relative_to(bin_dir.parent) for p in where.stdout.split()), where.stdout  # from the wheel
    done = _run([str(bin_dir / "ecas"), "--help"], tmp_path, env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: ecas ") and "ecas train-lm" in done.stdout
    for command in ("evaluate", "bench render"):
        done = _run([str(bin_dir / "ecas"), *command.split(), "--help"], tmp_path, env)
        assert done.returncode == 0, done.stderr
        assert done.stdout.startswith(f"usage: ecas {command} ")
    assert len(COMMANDS) > 20


def test_ecas_speaks_the_packaged_example_from_another_directory(installed, tmp_path):
    bin_dir, env = installed
    example = _run(
        [str(bin_dir / "python"), "-c", "from ecas.core.paths import EXAMPLES_DIR; print(EXAMPLES_DIR)"], tmp_path, env
    ).stdout.strip()
    wav = Path(example) / "librivox_0870.wav"
    assert wav.is_file() and wav.is_relative_to(bin_dir.parent)
    env = {**env, "OPENBLAS_NUM_THREADS": "1"}
    done = _run([str(bin_dir / "ecas"), "--speak", str(wav), "--headless", "--report", "report"], tmp_path, env)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    motion = np.load(tmp_path / "report" / "motion.npz")
    assert motion["poses"].shape[0] > 100 and np.isfinite(motion["poses"]).all()
    config = (tmp_path / "report" / "config.yaml").read_text()
    assert str(bin_dir.parent) in config and str(REPO) not in config  # checkpoints from the installed package
