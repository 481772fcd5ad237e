"""The top-level config: one frozen dataclass per YAML section, and the loader with `--set` overrides."""

from __future__ import annotations

import secrets
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from agent.dashboard.config import DashboardConfig
from dialogue.config import DialogueConfig
from ecas.core.bus import STAGES, BusConfig
from ecas.core.config import ConfigError, apply_override, build_dataclass, load_yaml, parse_override
from gesture.config import GestureConfig
from render.config import RenderConfig


@dataclass(frozen=True)
class IoConfig:
    """The user's side: where the user's audio comes from and whether the agent is heard."""

    source: Literal["mic", "replay", "silence"] = "replay"
    replay_path: Path | None = None
    tail_silence_s: float = 6.0  # after a replay, so the agent can answer the last words
    silence_s: float = 10.0  # length of a `silence` source
    speaker: bool = False
    input_device: str | None = None
    output_device: str | None = None

    def __post_init__(self):
        if self.tail_silence_s < 0:
            raise ConfigError(f"io.tail_silence_s: must be >= 0, got {self.tail_silence_s}")


@dataclass(frozen=True)
class RunConfig:
    """How the run is paced, which stages run, and where it reports.

    `components` replaces a stage's component factory (`stage: "module:function"`, called with the stage's
    section config and the RunContext), to plug in your own dialogue system, generator or renderer.
    `spawn` lists the stages this host starts (default: all of `stages`); the others run on another host under
    `launch.py --worker`, reached over `tcp://` endpoints.
    """

    live: bool = True
    seed: int = 0
    report_dir: Path | None = None  # default: a new runs/<time>-<suffix>/
    stages: tuple[str, ...] = STAGES
    spawn: tuple[str, ...] | None = None
    components: dict[str, str] = field(default_factory=dict)

    @property
    def local_stages(self) -> tuple[str, ...]:
        return self.stages if self.spawn is None else tuple(s for s in self.stages if s in self.spawn)

    def __post_init__(self):
        if self.seed < 0:
            raise ConfigError(f"run.seed: must be >= 0 (--seed), got {self.seed}")
        if not self.stages or self.stages[0] != "io" or list(self.stages) != [s for s in STAGES if s in self.stages]:
            raise ConfigError(
                f"run.stages: must start with io and keep the order {', '.join(STAGES)}; got {list(self.stages)}"
            )
        unknown = sorted(set(self.spawn or ()) - set(self.stages))
        if unknown:
            raise ConfigError(f"run.spawn: {unknown[0]} is not in run.stages {list(self.stages)}")
        for stage, factory in self.components.items():
            if stage not in STAGES:
                raise ConfigError(f"run.components.{stage}: unknown stage (stages: {', '.join(STAGES)})")
            if ":" not in factory:
                raise ConfigError(f"run.components.{stage}: expected 'module:function', got {factory!r}")

    def make_report_dir(self, now: str) -> Path:
        """`report_dir` (created if needed), or a new `runs/<now>-<suffix>/` that no other run shares."""
        if self.report_dir:
            path = Path(self.report_dir)
            path.mkdir(parents=True, exist_ok=True)
            return path
        Path("runs").mkdir(exist_ok=True)
        while True:
            path = Path("runs") / f"{now}-{secrets.token_hex(3)}"
            try:
                path.mkdir()  # atomic: exactly one run creates it
                return path
            except FileExistsError:
                continue


@dataclass(frozen=True)
class AppConfig:
    run: RunConfig = field(default_factory=RunConfig)
    bus: BusConfig = field(default_factory=BusConfig)
    io: IoConfig = field(default_factory=IoConfig)
    dialogue: DialogueConfig = field(default_factory=DialogueConfig)
    gesture: GestureConfig = field(default_factory=GestureConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    dashboard: DashboardConfig = field(default_factory=DashboardConfig)

    def __post_init__(self):
        if self.run.spawn is not None and self.bus.transport == "ipc" and not self.bus.endpoints:
            raise ConfigError("run.spawn: stages on other hosts need bus.transport: tcp (or tcp bus.endpoints)")
        if self.run.spawn is not None and self.bus.transport == "tcp" and self.bus.base_port == 0:
            raise ConfigError(
                "bus.base_port: 0 (free ports) needs every stage on this host; with run.spawn the "
                "hosts must agree on ports: give a base port"
            )


def load_app_config(path: Path | str, overrides: Sequence[str] = ()) -> AppConfig:
    """Read a YAML file, apply `section.key=value` overrides, and build the frozen config."""
    tree = load_yaml(Path(path))
    for text in overrides:
        apply_override(tree, *parse_override(text))
    return build_dataclass(AppConfig, tree)
