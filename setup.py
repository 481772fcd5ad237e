"""setuptools' build step (the rest of the project's metadata is in pyproject.toml): the wheel carries the
JavaScript the dashboard's page imports in render.mode browser (three.js, three-vrm), copied from the checkout's
`node_modules` (`npm ci`) into `agent/dashboard/vendor/` by `agent/dashboard/vendor.py`. Without node_modules the
wheel is still built, without them; browser mode then says what to run."""

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent


def _vendor_module():
    """agent/dashboard/vendor.py, loaded by its path (stdlib only: the package is not importable at build time)."""
    spec = importlib.util.spec_from_file_location("_ecas_dashboard_vendor", HERE / "agent" / "dashboard" / "vendor.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BuildPyWithVendor(build_py):
    """build_py, then the page's JavaScript into the build's copy of agent/dashboard (not into the checkout)."""

    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):  # an editable install serves the checkout's node_modules
            return
        vendor = _vendor_module()
        copied = vendor.copy_vendor(HERE / "node_modules", Path(self.build_lib) / "agent" / "dashboard" / "vendor")
        if copied:
            print(f"ecas: {len(copied)} JavaScript files for the dashboard's page copied from node_modules")
        else:
            print(
                "ecas: warning: no node_modules/three (run `npm ci`): this wheel cannot draw render.mode browser's page"
            )


setup(cmdclass={"build_py": BuildPyWithVendor})
