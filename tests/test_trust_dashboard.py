"""Issue 46, case 2: the dashboard answers only its own names (DNS rebinding), and beyond loopback only with the
token the console prints. Raw HTTP requests, as a rebinding page's browser or a script would send them."""

from __future__ import annotations

import asyncio
import re
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from agent.dashboard.access import TOKEN_COOKIE
from agent.dashboard.server import Hub, make_app, start_server
from tests.test_runtime import finish, launch, leftovers

WS_KEY = "dGhlIHNhbXBsZSBub25jZQ=="


class Server:
    """The dashboard's web app in a thread of its own (its asyncio loop), on a free loopback port."""

    def __init__(self, host: str, token: str | None = None):
        self.loop = asyncio.new_event_loop()
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        hub = Hub(lambda: [{"type": "hello"}], lambda _command: None)
        self.runner, self.port = asyncio.run_coroutine_threadsafe(
            start_server(make_app(hub, host, token), "127.0.0.1", 0), self.loop
        ).result()

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.runner.cleanup(), self.loop).result()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join()


def raw(port: int, path: str = "/", host: str | None = "127.0.0.1", headers: dict | None = None) -> tuple[int, str]:
    """Send one request as bytes; (status, response head)."""
    lines = [f"GET {path} HTTP/1.1"]
    if host is not None:
        lines.append(f"Host: {host}" if host.startswith("[") or ":" in host else f"Host: {host}:{port}")
    lines += [f"{k}: {v}" for k, v in (headers or {}).items()] + ["Connection: close", "", ""]
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall("\r\n".join(lines).encode())
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
    head = data.split(b"\r\n\r\n", 1)[0].decode("latin1")
    return int(head.split()[1]), head


def upgrade(origin: str | None) -> dict:
    headers = {"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Key": WS_KEY}
    headers["Sec-WebSocket-Version"] = "13"
    return headers | ({"Origin": origin} if origin else {})


@pytest.fixture
def loopback_server():
    server = Server("127.0.0.1")
    yield server
    server.close()


@pytest.fixture
def public_server():
    server = Server("0.0.0.0", token="s3cret-token")
    yield server
    server.close()


def ws_raw(port: int, host: str, origin: str | None, path: str = "/ws", extra: dict | None = None) -> int:
    headers = upgrade(origin) | (extra or {})
    headers.pop("Connection")  # raw() adds "Connection: close"; a WebSocket upgrade needs "Upgrade"
    lines = [f"GET {path} HTTP/1.1", f"Host: {host}", *[f"{k}: {v}" for k, v in headers.items()]]
    lines += ["Connection: Upgrade", "", ""]
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall("\r\n".join(lines).encode())
        s.settimeout(30)
        head = s.recv(4096).decode("latin1")
    return int(head.split()[1])


@pytest.mark.parametrize("path", ["/", "/state.json", "/static/dashboard.js"])
def test_http_answers_its_own_names_only(loopback_server, path):
    port = loopback_server.port
    for host in ("127.0.0.1", "localhost", f"[::1]:{port}", "LOCALHOST"):
        assert raw(port, path, host)[0] == 200, host
    for host in ("evil.example", "127.0.0.1.evil.example", "192.168.1.20", "[::1"):
        assert raw(port, path, host)[0] == 421, host
    assert raw(port, path, host=None)[0] in (400, 421)  # no Host at all (aiohttp itself refuses HTTP/1.1 without)
    status, _ = raw(port, path, "127.0.0.1", {"Origin": "http://evil.example:8998"})
    assert status == 403


def test_a_rebinding_pages_websocket_is_refused(loopback_server):
    """The measured attack: Host and Origin both evil.example (then only the Origin, then a null Origin)."""
    port = loopback_server.port
    assert ws_raw(port, f"evil.example:{port}", f"http://evil.example:{port}") == 421
    assert ws_raw(port, f"127.0.0.1:{port}", f"http://evil.example:{port}") == 403
    assert ws_raw(port, f"127.0.0.1:{port}", "null") == 403
    assert ws_raw(port, f"127.0.0.1:{port}", f"http://localhost:{port}") == 403  # its own name, another origin
    assert ws_raw(port, f"127.0.0.1:{port}", f"http://127.0.0.1:{port}") == 101
    assert ws_raw(port, f"localhost:{port}", None) == 101


def test_beyond_loopback_every_request_needs_the_token(public_server):
    port = public_server.port
    assert raw(port, "/")[0] == 403
    assert raw(port, "/?token=wrong")[0] == 403
    status, head = raw(port, "/?token=s3cret-token")
    assert status == 200
    cookie = re.search(rf"Set-Cookie: ({TOKEN_COOKIE}=[^;]+);.*SameSite=Strict", head, re.I)
    assert cookie and "HttpOnly" in head, head
    assert raw(port, "/static/dashboard.js", headers={"Cookie": cookie.group(1)})[0] == 200
    assert raw(port, "/state.json")[0] == 403
    assert ws_raw(port, f"127.0.0.1:{port}", f"http://127.0.0.1:{port}") == 403
    assert ws_raw(port, f"127.0.0.1:{port}", f"http://127.0.0.1:{port}", extra={"Cookie": cookie.group(1)}) == 101
    # A wildcard bind answers the machine's host name and IP literals, never another name, token or not.
    assert raw(port, "/?token=s3cret-token", socket.gethostname())[0] == 200
    assert raw(port, "/?token=s3cret-token", "10.1.2.3")[0] == 200
    assert raw(port, "/?token=s3cret-token", "evil.example")[0] == 421


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_a_run_beyond_loopback_prints_the_url_with_its_token(tmp_path):
    """launch.py --host 0.0.0.0: a warning naming the option, the URL with its token, which alone opens the page."""
    wav = tmp_path / "talk.wav"
    sf.write(wav, np.zeros(16000, np.float32), 16000)
    port = free_port()
    args = ["--replay", str(wav), "--host", "0.0.0.0", "--set", f"dashboard.port={port}"]
    proc = launch([*args, "--set", "dashboard.wait_for_start=true"], tmp_path / "run")
    url_file = tmp_path / "run" / "dashboard.url"
    deadline = time.monotonic() + 120
    while not url_file.exists():
        assert proc.poll() is None and time.monotonic() < deadline, "the dashboard never served"
        time.sleep(0.1)
    token = url_file.read_text().strip().rsplit("?token=", 1)[1]
    assert raw(port, "/")[0] == 403
    assert raw(port, f"/?token={token}")[0] == 200
    assert raw(port, f"/?token={token}", "evil.example")[0] == 421
    proc.send_signal(signal.SIGINT)
    code, output = finish(proc)
    assert code == 130, output
    assert "dashboard.host / --host" in output and f"?token={token}" in output, output
    assert not leftovers(proc.pid)
    assert not list(Path("/tmp").glob(f"ecas-{proc.pid}-*"))
