"""A minimal headless-Chromium driver over the DevTools protocol (aiohttp WebSocket client), for the dashboard's
browser test and its README screenshot. Uses the system's Chromium; never downloads a browser.

    async with HeadlessChromium(url) as page:
        await page.wait_for("window.dashboard.frames > 0", timeout_s=20)
        await page.screenshot(Path("docs/dashboard.png"))

    python -m agent.dashboard.browser http://127.0.0.1:8998/ out.png --wait "window.dashboard.frames > 10"
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import itertools
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import aiohttp

BROWSER_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
BROWSER_ENV = "CHROMIUM"  # an explicit browser binary
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--autoplay-policy=no-user-gesture-required",
    "--remote-debugging-port=0",
)
START_TIMEOUT_S = 30.0
CLOSE_TIMEOUT_S = 5.0


class BrowserError(RuntimeError):
    pass


def find_chromium() -> str | None:
    """The browser binary: $CHROMIUM, else the first of BROWSER_NAMES on PATH; None when there is none."""
    explicit = os.environ.get(BROWSER_ENV)
    if explicit:
        return explicit if shutil.which(explicit) else None
    return next((path for path in map(shutil.which, BROWSER_NAMES) if path), None)


class HeadlessChromium:
    """One headless Chromium with a fresh profile, showing `url` in a `width`×`height` window; `flags` are
    added to the command line (e.g. Chromium's fake microphone for tests)."""

    def __init__(
        self, url: str, width: int = 1280, height: int = 1000, binary: str | None = None, flags: Sequence[str] = ()
    ):
        self.url, self.width, self.height, self.flags = url, width, height, tuple(flags)
        self.binary = binary or find_chromium()
        if self.binary is None:
            raise BrowserError(f"no Chromium found (looked for ${BROWSER_ENV} and {', '.join(BROWSER_NAMES)})")
        self._ids = itertools.count(1)

    async def __aenter__(self) -> HeadlessChromium:
        self.profile = Path(tempfile.mkdtemp(prefix="dash-chromium-"))
        self.process = subprocess.Popen(
            [
                self.binary,
                *FLAGS,
                *self.flags,
                f"--user-data-dir={self.profile}",
                f"--window-size={self.width},{self.height}",
                self.url,
            ],
            stdout=subprocess.DEVNULL,
            stderr=open(self.profile / "stderr.log", "wb"),
            start_new_session=True,  # its own process group: its renderer and GPU processes go with it
        )
        self.session = aiohttp.ClientSession()
        try:
            port = await self._devtools_port()
            self.ws = await self.session.ws_connect(await self._page_socket(port), max_msg_size=0)
            await self.call(
                "Emulation.setDeviceMetricsOverride",
                width=self.width,
                height=self.height,
                deviceScaleFactor=1,
                mobile=False,
            )
        except BaseException:
            await self.__aexit__(None, None, None)
            raise
        return self

    async def __aexit__(self, *exc) -> None:
        try:
            if getattr(self, "ws", None) is not None:
                await self._close_browser()
                await self.ws.close()
            await self.session.close()
        finally:
            self.kill()
            shutil.rmtree(self.profile, ignore_errors=True)

    def kill(self) -> None:
        """End the browser and every process of its group (SIGTERM, then SIGKILL after CLOSE_TIMEOUT_S)."""
        if self.process.poll() is None:
            self.process.terminate()
        try:
            self.process.wait(CLOSE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.process.pid, signal.SIGKILL)  # children left behind by a browser that was killed

    @property
    def pid(self) -> int:
        return self.process.pid

    async def _close_browser(self) -> None:
        """Ask Chromium to quit: unlike SIGTERM, it then removes its temporary directory (singleton socket)."""
        # TypeError: aiohttp's answer to a socket closed while a reply was awaited
        with contextlib.suppress(BrowserError, asyncio.TimeoutError, aiohttp.ClientError, ConnectionError, TypeError):
            await asyncio.wait_for(self.call("Browser.close"), CLOSE_TIMEOUT_S)
        with contextlib.suppress(subprocess.TimeoutExpired):
            await asyncio.to_thread(self.process.wait, CLOSE_TIMEOUT_S)

    async def _devtools_port(self) -> int:
        marker = self.profile / "DevToolsActivePort"
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise BrowserError(
                    f"{self.binary} exited with code {self.process.returncode}: "
                    f"{(self.profile / 'stderr.log').read_text(errors='replace')[-800:]}"
                )
            lines = marker.read_text().split() if marker.exists() else []
            if lines:
                return int(lines[0])
            await asyncio.sleep(0.05)
        raise BrowserError(f"{self.binary} did not open its DevTools port within {START_TIMEOUT_S:.0f} s")

    async def _page_socket(self, port: int) -> str:
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            async with self.session.get(f"http://127.0.0.1:{port}/json/list") as response:
                pages = [t for t in await response.json() if t.get("type") == "page"]
            if pages:
                return pages[0]["webSocketDebuggerUrl"]
            await asyncio.sleep(0.05)
        raise BrowserError("the browser opened no page")

    async def call(self, method: str, **params: Any) -> dict:
        """One DevTools command; events that arrive meanwhile are ignored."""
        call_id = next(self._ids)
        await self.ws.send_json({"id": call_id, "method": method, "params": params})
        while True:
            msg = await self.ws.receive_json()
            if msg.get("id") == call_id:
                if "error" in msg:
                    raise BrowserError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    async def evaluate(self, expression: str) -> Any:
        """The JSON value of a JavaScript expression in the page (promises are awaited)."""
        result = await self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            raise BrowserError(f"{expression!r} threw: {details.get('exception', {}).get('description', details)}")
        return result["result"].get("value")

    async def wait_for(self, expression: str, timeout_s: float, poll_s: float = 0.1) -> Any:
        """Poll until the expression is truthy (an exception, e.g. while the page loads, counts as false)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                value = await self.evaluate(expression)
            except BrowserError as e:
                value = e
            if value and not isinstance(value, BrowserError):
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"{expression!r} still {value!r} after {timeout_s:.0f} s")
            await asyncio.sleep(poll_s)

    async def screenshot(self, path: Path) -> None:
        data = await self.call("Page.captureScreenshot", format="png")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(base64.b64decode(data["data"]))


async def _snapshot(url: str, out: Path, wait: str | None, timeout_s: float, width: int, height: int) -> None:
    async with HeadlessChromium(url, width, height) as page:
        if wait:
            await page.wait_for(wait, timeout_s)
        await page.screenshot(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="ecas screenshot", description="Screenshot a dashboard page with headless Chromium."
    )
    p.add_argument("url")
    p.add_argument("out", type=Path)
    p.add_argument("--wait", metavar="JS", help="a JavaScript condition to wait for before the screenshot")
    p.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for --wait (default %(default)s)")
    p.add_argument("--size", default="1280x1000", help="window size WxH (default %(default)s)")
    args = p.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    try:
        asyncio.run(_snapshot(args.url, args.out, args.wait, args.timeout, width, height))
    except (BrowserError, TimeoutError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
