"""Options of the `gesture:` section of the YAML config (placeholder: the owner of gesture/ extends it)."""

from dataclasses import dataclass


@dataclass(frozen=True)
class GestureConfig:
    pass
