"""Options of the `dialogue:` section of the YAML config (placeholder: the owner of dialogue/ extends it)."""

from dataclasses import dataclass


@dataclass(frozen=True)
class DialogueConfig:
    pass
