"""Options of the `dashboard:` section of the YAML config."""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass
from pathlib import Path

from ecas.core.config import ConfigError

LOOPBACK_NAMES = ("localhost",)


@dataclass(frozen=True)
class DashboardConfig:
    """The live dashboard: a web page served by its own process (not a pipeline stage).

    It listens on `host:port` (127.0.0.1 keeps it on this machine; port 0 takes any free port, written to
    `<run dir>/dashboard.url`). With `wait_for_start`, the run waits for the page's Start button.
    `browser_mic` lets a page send its microphone as the user's audio (set by `launch.py --browser-mic`, which
    also plugs the matching io source in). Browsers give a page the microphone only on https or localhost:
    from another machine, give `tls_cert` and `tls_key` (PEM files) or forward the port over ssh.
    `jpeg_quality` encodes frames the render stage sends as raw RGB. `history_steps` is how many latency
    samples and `max_turns` how many transcript turns a newly opened page receives.
    """

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 8998
    wait_for_start: bool = False
    browser_mic: bool = False
    tls_cert: Path | None = None
    tls_key: Path | None = None
    jpeg_quality: int = 80
    history_steps: int = 250
    max_turns: int = 40

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"dashboard.port: must be in [0, 65535], got {self.port}")
        if not self.host:
            raise ConfigError("dashboard.host: must not be empty (127.0.0.1 keeps the page on this machine)")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"dashboard.jpeg_quality: must be in [1, 100], got {self.jpeg_quality}")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ConfigError("dashboard.tls_cert: tls_cert and tls_key must be given together")
        for name in ("history_steps", "max_turns"):
            if getattr(self, name) < 1:
                raise ConfigError(f"dashboard.{name}: must be >= 1, got {getattr(self, name)}")

    @property
    def loopback_only(self) -> bool:
        """True when only this machine can reach the page."""
        if self.host in LOOPBACK_NAMES:
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False
