"""The JavaScript the page imports in render.mode browser: three.js and @pixiv/three-vrm (both MIT, from npm).

They are found in the installed package's own copy (`agent/dashboard/vendor/<name>/`, which setup.py's build step
copies into the wheel from the checkout's `node_modules`) or else in the checkout's `node_modules` (`npm ci`).
Only the files the page imports are copied: the entry modules below and every module they import by a relative
path, with the package's LICENSE beside them. Bare specifiers (`three`, `three/addons/...`) are the page's import
map (static/index.html), not followed.

Standard library only: setup.py loads this file by its path at build time, before the package is installed.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent / "vendor"  # the wheel's copy
NODE_MODULES = Path(__file__).resolve().parents[2] / "node_modules"  # a checkout's `npm ci`
# URL name (/vendor/<name>/) -> (npm package, the modules the page imports from it)
ENTRIES = {
    "three": ("three", ("build/three.module.js", "examples/jsm/loaders/GLTFLoader.js")),
    "three-vrm": ("@pixiv/three-vrm", ("lib/three-vrm.module.min.js",)),
}
LICENSE = "LICENSE"
RELATIVE_IMPORT = re.compile(r"""(?:\bfrom|\bimport)\s*\(?\s*(['"])(\.{1,2}/[^'"]+)\1""")


def module_closure(root: Path, entries: tuple[str, ...]) -> list[str]:
    """The entry modules and every module they import by a relative path, as paths relative to `root`, sorted;
    FileNotFoundError names the first one missing."""
    seen: set[str] = set()
    todo = list(entries)
    while todo:
        rel = todo.pop()
        if rel in seen:
            continue
        seen.add(rel)
        path = root / rel
        if not path.is_file():
            raise FileNotFoundError(f"{path}: a module the dashboard's page imports is missing")
        for _, spec in RELATIVE_IMPORT.findall(path.read_text(encoding="utf-8")):
            todo.append((Path(rel).parent / spec).as_posix())
    return sorted(_normalise(rel) for rel in seen)


def _normalise(rel: str) -> str:
    parts: list[str] = []
    for part in rel.split("/"):
        if part == "..":
            parts.pop()
        elif part not in (".", ""):
            parts.append(part)
    return "/".join(parts)


def vendor_files(node_modules: Path = NODE_MODULES) -> dict[str, list[str]]:
    """URL name -> the files to copy from its npm package (relative paths, LICENSE included)."""
    return {
        name: [*module_closure(node_modules / package, entries), LICENSE]
        for name, (package, entries) in ENTRIES.items()
    }


def copy_vendor(node_modules: Path, dest: Path) -> list[str]:
    """The build step: copy the page's modules from `node_modules` into `dest/<name>/`; returns the files copied
    (relative to dest), or [] when node_modules lacks them (the wheel is then built without them, and browser mode
    says what to run)."""
    shutil.rmtree(dest, ignore_errors=True)  # a previous build's copy must not outlive its node_modules
    try:
        files = vendor_files(node_modules)
    except FileNotFoundError:
        return []
    copied = []
    for name, rels in files.items():
        package = ENTRIES[name][0]
        for rel in rels:
            target = dest / name / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(node_modules / package / rel, target)
            copied.append(f"{name}/{rel}")
    return copied


def vendor_dir(name: str) -> Path:
    """Where /vendor/<name>/ is served from: the package's copy if it holds the entry modules, else node_modules
    (which may be missing: `missing()` says so)."""
    package, entries = ENTRIES[name]
    if all((PACKAGE_DIR / name / e).is_file() for e in entries):
        return PACKAGE_DIR / name
    return NODE_MODULES / package


def missing() -> str:
    """'' when the page's modules are all there, else one line naming what is missing and what to run."""
    absent = [f"{n}/{e}" for n, (_, entries) in ENTRIES.items() for e in entries if not (vendor_dir(n) / e).is_file()]
    if not absent:
        return ""
    return (
        f"render.mode browser: the page's JavaScript is not installed ({', '.join(absent)} is neither in "
        f"{PACKAGE_DIR} nor in {NODE_MODULES}); run `npm ci` in the checkout, then `pip install <checkout>` again "
        "(or run from the checkout), or use render.mode=server"
    )
