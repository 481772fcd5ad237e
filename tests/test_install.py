"""The installed package runs from another directory: a wheel built from this checkout holds every file a module
reads from beside itself, and installed into a new virtual environment it answers `ecas --help` and speaks the
packaged example from a working directory that is not the checkout.

The new environment reuses this one's third-party packages (a `.pth` line naming its site-packages, whose own `.pth`
files, such as an editable install's, are then not run) and gets the wheel with `--no-deps`: the project's own
modules come only from the wheel. `pip install <checkout>` into a truly fresh environment, which also resolves the
requirements, takes minutes and is timed in docs/install.md.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import numpy as np
import pytest

from agent.dashboard.vendor import ENTRIES, NODE_MODULES, vendor_files
from ecas.cli import COMMANDS

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("ecas", "agent", "dialogue", "gesture", "render", "bench")
SOURCE_TOP_SKIP = {"build", "runs", "out", "cache", "data", "tests", "docs", "scripts", "node_modules"}


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


def _copy_page_modules(source: Path) -> None:
    """The checkout's node_modules, cut to the files the build step copies (three.js alone is 24 MB)."""
    for name, rels in vendor_files().items():
        for rel in rels:
            target = source / "node_modules" / ENTRIES[name][0] / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(NODE_MODULES / ENTRIES[name][0] / rel, target)


needs_node_modules = pytest.mark.skipif(
    not (NODE_MODULES / "three").is_dir() or not (NODE_MODULES / "@pixiv" / "three-vrm").is_dir(),
    reason="needs the page's JavaScript in node_modules (`npm ci`)",
)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built from a copy of the checkout (the build leaves nothing in the checkout itself), with the
    page's JavaScript in its node_modules when this checkout has it."""
    root = tmp_path_factory.mktemp("wheel")
    source = root / "source"
    shutil.copytree(REPO, source, ignore=_source_skip, symlinks=False)
    if (NODE_MODULES / "three").is_dir() and (NODE_MODULES / "@pixiv" / "three-vrm").is_dir():
        _copy_page_modules(source)
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


# The page's JavaScript (agent.dashboard.vendor): what the page imports, copied in by setup.py's build step.
PAGE_MODULES = (
    "agent/dashboard/vendor/three/build/three.module.js",
    "agent/dashboard/vendor/three/build/three.core.js",
    "agent/dashboard/vendor/three/examples/jsm/loaders/GLTFLoader.js",
    "agent/dashboard/vendor/three/examples/jsm/utils/BufferGeometryUtils.js",
    "agent/dashboard/vendor/three/LICENSE",
    "agent/dashboard/vendor/three-vrm/lib/three-vrm.module.min.js",
    "agent/dashboard/vendor/three-vrm/LICENSE",
)
MAX_VENDOR_BYTES = 4_000_000  # uncompressed; three.js's whole npm package is 24 MB


@needs_node_modules
def test_the_wheel_carries_only_the_javascript_the_page_imports(wheel):
    archive = zipfile.ZipFile(wheel)
    vendored = {i.filename: i for i in archive.infolist() if i.filename.startswith("agent/dashboard/vendor/")}
    missing = [name for name in PAGE_MODULES if name not in vendored]
    assert not missing, f"not in the wheel: {missing}"
    assert "MIT License" in archive.read("agent/dashboard/vendor/three/LICENSE").decode()
    assert "MIT License" in archive.read("agent/dashboard/vendor/three-vrm/LICENSE").decode()
    expected = {f"agent/dashboard/vendor/{n}/{rel}" for n, rels in vendor_files().items() for rel in rels}
    assert set(vendored) == expected  # nothing else of the npm packages (no src/, no examples not imported)
    raw = sum(i.file_size for i in vendored.values())
    packed = sum(i.compress_size for i in vendored.values())
    assert raw < MAX_VENDOR_BYTES
    print(
        f"wheel {wheel.stat().st_size / 1e6:.1f} MB; "
        f"the page's JavaScript {raw / 1e6:.2f} MB, {packed / 1e6:.2f} MB packed"
    )


def test_every_module_the_page_imports_is_vendored():
    """The page's modules' imports (static/*.js), through the import map of index.html or as /vendor/ URLs, are
    files the build copies (or the page's own /static/ files, package data)."""
    static = REPO / "agent" / "dashboard" / "static"
    html = (static / "index.html").read_text()
    imports = json.loads(re.search(r'<script type="importmap">(.*?)</script>', html, re.S).group(1))["imports"]
    specifiers = set()
    for module in static.glob("*.js"):
        source = module.read_text()
        specifiers |= set(re.findall(r"""(?:^import .*? from |\bimport\()\s*["']([^"'$]+)["']""", source, re.M))
        specifiers |= set(re.findall(r"""^export const \w+_MODULE = ["']([^"']+)["']""", source, re.M))
    assert "three" in specifiers and any("three-vrm" in s for s in specifiers), specifiers
    files = vendor_files() if (NODE_MODULES / "three").is_dir() else None
    for spec in specifiers - {"/static/avatar.js"}:
        url = imports.get(spec) or next(
            (v + spec[len(k) :] for k, v in imports.items() if k.endswith("/") and spec.startswith(k)), spec
        )
        if url.startswith("/static/"):
            assert (static / url[len("/static/") :]).is_file(), url
            continue
        assert url.startswith("/vendor/"), spec
        name, rel = url[len("/vendor/") :].split("/", 1)
        assert name in ENTRIES and (files is None or rel in files[name]), url


SERVE_VENDOR = """
import asyncio, json, sys
import aiohttp
from agent.dashboard.server import Hub, make_app, start_server

async def main():
    runner, port = await start_server(make_app(Hub(lambda: [], lambda _c: None)), "127.0.0.1", 0)
    out = {}
    try:
        async with aiohttp.ClientSession() as session:
            for path in sys.argv[1:]:
                async with session.get(f"http://127.0.0.1:{port}{path}") as r:
                    out[path] = [r.status, len(await r.read()), r.headers.get("Content-Type", "")]
    finally:
        await runner.cleanup()
    print(json.dumps(out))

asyncio.run(main())
"""


@needs_node_modules
def test_the_installed_dashboard_serves_the_pages_javascript_and_browser_mode_needs_it(installed, tmp_path):
    """The installed server (no checkout, no node_modules beside it) serves /vendor/ from the package's copy; with
    that copy gone, `ecas --set render.mode=browser` stops before any stage with one line naming `npm ci`."""
    bin_dir, env = installed
    paths = [
        "/vendor/three/build/three.module.js",
        "/vendor/three/build/three.core.js",
        "/vendor/three/examples/jsm/loaders/GLTFLoader.js",
        "/vendor/three-vrm/lib/three-vrm.module.min.js",
        "/vendor/three/src/Three.js",  # not shipped
    ]
    done = _run([str(bin_dir / "python"), "-c", SERVE_VENDOR, *paths], tmp_path, env)
    assert done.returncode == 0, done.stderr
    served = json.loads(done.stdout)
    for path in paths[:-1]:
        status, size, kind = served[path]
        assert status == 200 and size > 10_000 and "javascript" in kind, (path, served[path])
    assert served[paths[-1]][0] == 404
    where = _run(
        [str(bin_dir / "python"), "-c", "from agent.dashboard.vendor import vendor_dir; print(vendor_dir('three'))"],
        tmp_path,
        env,
    ).stdout.strip()
    vendor = Path(where).parent
    assert vendor.is_relative_to(bin_dir.parent) and vendor.name == "vendor"
    hidden = vendor.with_name("vendor-hidden")
    vendor.rename(hidden)
    try:
        args = ["--replay", str(REPO / "ecas" / "examples" / "librivox_0870.wav"), "--set", "render.mode=browser"]
        done = _run([str(bin_dir / "ecas"), *args, "--report", "report"], tmp_path, env)
    finally:
        hidden.rename(vendor)
    assert done.returncode == 2, done.stdout[-2000:] + done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert lines[-1].startswith("error: render.mode browser:") and "npm ci" in lines[-1], done.stderr[-2000:]
    assert not (tmp_path / "report").exists() or not any((tmp_path / "report").iterdir())
