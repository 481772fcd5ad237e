"""The dashboard's web server (aiohttp): the page, its static assets, a state snapshot and one WebSocket per page.

The WebSocket pushes JSON events (text messages) and frames / agent audio (binary messages, see
`events.pack_binary`). Every page has its own sender: when a page falls behind, only its newest few frames wait
(older ones are skipped and counted), so a slow browser never holds up the bus or other pages.
A page sends `{"type": "control", "command": "start" | "stop"}`, `{"type": "audio", "enabled": bool}` (the
agent's voice), `{"type": "motion", "enabled": bool}` (the motion stream, docs/motion_stream.md) and, with the
browser microphone, `{"type": "mic", "enabled": bool}` then binary int16 PCM at 24 kHz (header kind BINARY_MIC);
one page at a time holds the microphone.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import ssl
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from urllib.parse import urlsplit

from aiohttp import WSCloseCode, WSMsgType, web

from agent.dashboard.access import access_middleware
from agent.dashboard.events import BINARY_HEADER, BINARY_MIC, Event
from agent.dashboard.vendor import ENTRIES, missing, vendor_dir

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"
THREE_DIR = vendor_dir("three")  # the wheel's copy, else the checkout's node_modules (agent.dashboard.vendor)
MAX_PENDING_EVENTS = 2000  # a page this far behind is disconnected; it reconnects and gets a snapshot
MAX_PENDING_AUDIO = 25  # steps of agent audio (2 s)
MAX_PENDING_FRAMES = 4  # the render stage publishes a step's two frames together
MAX_PENDING_MOTION = 50  # steps of motion (4 s); a page further behind skips the oldest (counted)
COMMANDS = ("start", "stop")
AVATAR_FILES = web.AppKey("avatar_files", object)


class Page:
    """One connected page and its pending messages."""

    def __init__(self, ws: web.WebSocketResponse):
        self.ws = ws
        self.events: collections.deque[str] = collections.deque()
        self.audio: collections.deque[bytes] = collections.deque(maxlen=MAX_PENDING_AUDIO)
        self.frames: collections.deque[bytes] = collections.deque(maxlen=MAX_PENDING_FRAMES)
        self.motion: collections.deque[bytes] = collections.deque(maxlen=MAX_PENDING_MOTION)
        self.wants_audio = False
        self.wants_motion = False
        self.skipped_frames = 0
        self.skipped_motion = 0
        self.wake = asyncio.Event()
        self.sending = False  # a batch of messages is on its way out
        self.reader: asyncio.Future | None = None  # reads the page's messages until it closes or the run ends
        self.finished = asyncio.Event()  # its connection is over

    def push_event(self, text: str) -> None:
        if len(self.events) >= MAX_PENDING_EVENTS:
            asyncio.ensure_future(self.ws.close(message=b"too far behind"))
            return
        self.events.append(text)
        self.wake.set()

    def push_frame(self, data: bytes) -> None:
        self.skipped_frames += self._push_bounded(self.frames, data)

    def push_motion(self, data: bytes) -> None:
        self.skipped_motion += self._push_bounded(self.motion, data)

    def _push_bounded(self, queue: collections.deque[bytes], data: bytes) -> int:
        """Append to a queue with a maxlen; 1 if its oldest message was dropped to make room, else 0."""
        dropped = int(len(queue) == queue.maxlen)
        queue.append(data)
        self.wake.set()
        return dropped

    def push_audio(self, data: bytes) -> None:
        if self.wants_audio:
            self.audio.append(data)
            self.wake.set()

    async def send_pending(self) -> None:
        while not self.ws.closed:
            await self.wake.wait()
            self.wake.clear()
            self.sending = True
            try:
                while self.events:
                    await self.ws.send_str(self.events.popleft())
                while self.audio:
                    await self.ws.send_bytes(self.audio.popleft())
                while self.motion:
                    await self.ws.send_bytes(self.motion.popleft())
                while self.frames:
                    await self.ws.send_bytes(self.frames.popleft())
            finally:
                self.sending = False

    @property
    def flushed(self) -> bool:
        return self.ws.closed or not (self.events or self.sending)


class Hub:
    """Fans events and frames out to every open page; passes the pages' commands to `on_command`."""

    def __init__(
        self,
        snapshot: Callable[[], Iterable[Event]],
        on_command: Callable[[str], None],
        on_mic: Callable[[bytes], None] | None = None,
        on_displayed: Callable[[int, float, float], None] | None = None,
    ):
        self.snapshot = snapshot
        self.on_command = on_command
        self.on_displayed = on_displayed  # (step, its display time on this host's monotonic clock ns, clock RTT ms)
        self.on_mic = on_mic  # None: no browser microphone in this run
        self.mic_page: Page | None = None
        self.pages: set[Page] = set()
        self.skipped_frames_closed = 0  # frames skipped by pages that have since closed
        self.skipped_motion_closed = 0

    def broadcast(self, event: Event) -> None:
        if self.pages:
            text = json.dumps(event, separators=(",", ":"))
            for page in self.pages:
                page.push_event(text)

    def broadcast_frame(self, data: bytes) -> None:
        for page in self.pages:
            page.push_frame(data)

    @property
    def motion_pages(self) -> list[Page]:
        return [page for page in self.pages if page.wants_motion]

    def broadcast_motion(self, data: bytes) -> None:
        for page in self.motion_pages:
            page.push_motion(data)

    def broadcast_audio(self, data: bytes) -> None:
        for page in self.pages:
            page.push_audio(data)

    async def send_last(self, event: Event, timeout_s: float = 2.0) -> None:
        """The run is over: every page drops the frames and audio it has not been sent yet and gets `event` after
        its other pending events; returns when all have them (a page that reads slowly, e.g. on a loaded machine, is
        waited for up to `timeout_s`)."""
        for page in self.pages:
            page.frames.clear()
            page.audio.clear()
            page.motion.clear()
        self.broadcast(event)
        deadline = time.monotonic() + timeout_s
        while not all(page.flushed for page in self.pages) and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        behind = sum(not page.flushed for page in self.pages)
        log.info(
            "last event %s sent to %d page(s)%s",
            event.get("phase", event.get("type")),
            len(self.pages) - behind,
            f"; {behind} still behind after {timeout_s:g} s" if behind else "",
        )

    async def close_pages(self, timeout_s: float = 1.0) -> None:
        """Close every page's WebSocket (they would otherwise hold the server's shutdown): each page's handler stops
        reading and closes it, waiting up to `timeout_s` for the page's answer.

        aiohttp's `close()` from another task than the reading one ends the connection without that answer; the
        page's messages that still arrive (its microphone) are then never read, the kernel resets the connection,
        and the page loses what it had not read yet, such as the last run state."""
        pages = list(self.pages)
        for page in pages:
            page.reader.cancel()
        if pages:
            await asyncio.wait([asyncio.ensure_future(page.finished.wait()) for page in pages], timeout=timeout_s)

    def counters(self) -> dict[str, int]:
        return {
            "pages": len(self.pages),
            "skipped_frames": self.skipped_frames_closed + sum(p.skipped_frames for p in self.pages),
            "skipped_motion": self.skipped_motion_closed + sum(p.skipped_motion for p in self.pages),
        }

    async def websocket(self, request: web.Request) -> web.WebSocketResponse:
        if not same_origin(request):
            raise web.HTTPForbidden(text="the dashboard accepts WebSockets from its own page only")
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=1 << 16)
        await ws.prepare(request)
        page = Page(ws)
        for event in self.snapshot():
            page.push_event(json.dumps(event, separators=(",", ":")))
        self.pages.add(page)
        log.info("page connected (%d open)", len(self.pages))
        sender = asyncio.ensure_future(page.send_pending())
        page.reader = asyncio.ensure_future(self._read(page))
        try:
            await asyncio.wait([page.reader])
            if page.reader.cancelled():  # close_pages stopped the reading: the run is over
                await ws.close(code=WSCloseCode.GOING_AWAY, message=b"the run ended")
            else:
                page.reader.result()  # the page closed; a failure in handling its messages is raised here
        finally:
            page.reader.cancel()
            if self.mic_page is page:
                self.mic_page = None
            self.pages.discard(page)
            self.skipped_frames_closed += page.skipped_frames
            self.skipped_motion_closed += page.skipped_motion
            sender.cancel()
            page.finished.set()
            log.info("page disconnected (close code %s, %d open)", ws.close_code, len(self.pages))
        return ws

    async def _read(self, page: Page) -> None:
        async for msg in page.ws:
            if msg.type == WSMsgType.TEXT:
                self._on_page_message(page, msg.data)
            elif msg.type == WSMsgType.BINARY:
                self._on_page_audio(page, msg.data)

    def _on_page_message(self, page: Page, text: str) -> None:
        try:
            msg = json.loads(text)
        except (ValueError, RecursionError):  # RecursionError: nested deeper than the parser's stack
            log.warning("ignored a page message that is not JSON (or nested too deep): %.80r", text)
            return
        if not isinstance(msg, dict):
            return
        if msg.get("type") == "control" and msg.get("command") in COMMANDS:
            log.info("page asked to %s", msg["command"])
            self.on_command(msg["command"])
        elif msg.get("type") == "audio":
            page.wants_audio = bool(msg.get("enabled"))
        elif msg.get("type") == "motion":
            page.wants_motion = bool(msg.get("enabled"))
        elif msg.get("type") == "clock" and isinstance(msg.get("t_page_ms"), (int, float)):
            # the page's NTP-style probe: it keeps the offset of its fastest round trip
            reply = {"type": "clock", "t_page_ms": msg["t_page_ms"], "t_server_ns": time.monotonic_ns()}
            page.push_event(json.dumps(reply))
        elif msg.get("type") == "displayed":
            self._on_displayed(msg)
        elif msg.get("type") == "mic":
            self._claim_mic(page, bool(msg.get("enabled")))
        else:
            log.warning("ignored an unknown page message: %.80r", text)

    def _on_displayed(self, msg: dict) -> None:
        """A page showed a step: `t_server_ns` is its display time on this host's clock (from its clock probes)."""
        step, t_ns, rtt = msg.get("step"), msg.get("t_server_ns"), msg.get("clock_rtt_ms")
        numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (step, t_ns, rtt))
        if self.on_displayed is not None and numbers and step >= 0:
            self.on_displayed(int(step), float(t_ns), float(rtt))

    def _claim_mic(self, page: Page, enabled: bool) -> None:
        if not enabled:
            if self.mic_page is page:
                self.mic_page = None
            return
        if self.on_mic is None:
            reason = "this run does not take the browser's microphone (launch.py --browser-mic)"
        elif self.mic_page not in (None, page):
            reason = "another page holds the microphone"
        else:
            self.mic_page, reason = page, ""
        page.push_event(json.dumps({"type": "mic", "granted": not reason, "reason": reason}))

    def _on_page_audio(self, page: Page, data: bytes) -> None:
        if page is not self.mic_page or len(data) <= BINARY_HEADER.size or data[0] != BINARY_MIC:
            return
        payload = data[BINARY_HEADER.size :]
        if len(payload) % 2 == 0:
            self.on_mic(payload)


def same_origin(request: web.Request) -> bool:
    """A browser sends Origin on a WebSocket: only the dashboard's own page may connect (no other web site)."""
    origin = request.headers.get("Origin")
    return origin is None or urlsplit(origin).netloc == request.host


def make_app(
    hub: Hub, host: str = "127.0.0.1", token: str | None = None, avatar: str | Path | None = None
) -> web.Application:
    """The page, its files, its state and its WebSocket, for requests that name `host` (agent.dashboard.access;
    with `token`, only for requests that carry it); `avatar` is the user's rig the page draws in render.mode browser
    (None: ours)."""
    from agent.dashboard.avatar_file import AvatarFiles

    app = web.Application(middlewares=[access_middleware(host, token)])
    app[AVATAR_FILES] = AvatarFiles(avatar)

    async def index(_request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC_DIR / "index.html")

    async def state(_request: web.Request) -> web.Response:
        return web.json_response({"events": list(hub.snapshot()), "counters": hub.counters()})

    app.router.add_get("/", index)
    app.router.add_get("/state.json", state)
    app.router.add_get("/ws", hub.websocket)
    app.router.add_get("/avatar.glb", avatar_glb)
    app.router.add_get("/avatar.json", avatar_spec)
    app.router.add_static("/static/", STATIC_DIR)
    for name in ENTRIES:  # /vendor/three/, /vendor/three-vrm/: the page's JavaScript, never from a CDN
        if vendor_dir(name).is_dir():
            app.router.add_static(f"/vendor/{name}/", vendor_dir(name))
    if missing():
        log.warning("%s", missing())
    return app


async def avatar_glb(request: web.Request) -> web.Response:
    """The avatar the page draws: the user's rig, or ours as a skinned GLB (built once, then cached on disk)."""
    path = await asyncio.get_running_loop().run_in_executor(None, request.app[AVATAR_FILES].glb)
    return web.FileResponse(path, headers={"Content-Type": "model/gltf-binary"})


async def avatar_spec(request: web.Request) -> web.Response:
    """How the page drives the avatar's bones and face from SMPL-X motion (render.rig.Rig.spec)."""
    spec = await asyncio.get_running_loop().run_in_executor(None, request.app[AVATAR_FILES].spec)
    return web.json_response(spec)


async def start_server(
    app: web.Application, host: str, port: int, tls: tuple[str, str] | None = None
) -> tuple[web.AppRunner, int]:
    """Listen on host:port (https with `tls` = (cert, key) PEM paths); returns the runner and the bound port
    (port 0: any free one)."""
    ssl_context = None
    if tls is not None:
        ssl_context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        ssl_context.load_cert_chain(*tls)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, host, port, ssl_context=ssl_context)
    try:
        await site.start()
    except OSError as e:
        await runner.cleanup()
        raise OSError(
            f"dashboard: cannot listen on {host}:{port} ({e.strerror or e}); "
            f"set another dashboard.port or stop what uses it"
        ) from None
    bound = runner.addresses[0][1]
    return runner, bound
