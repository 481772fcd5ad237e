"""Options of the `render:` section of the YAML config (placeholder: the owner of render/ extends it)."""

from dataclasses import dataclass


@dataclass(frozen=True)
class RenderConfig:
    pass
