"""The conversation as turns with per-word times for both sides, written to the run's transcript.json."""

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ecas.core.atomic import write_text_atomic


@dataclass
class Word:
    word: str
    start_s: float
    end_s: float


@dataclass
class Turn:
    speaker: str  # "user" or "agent"
    start_s: float
    end_s: float
    words: list[Word] = field(default_factory=list)
    text: str = ""  # agent: the full text it meant to say; user: the recognised words
    interrupted: bool = False  # agent only: cut by the user's barge-in
    interrupted_at_word: int | None = None  # index of the word being spoken when it stopped (not completed)
    answered: bool | None = None  # user only: whether the agent replied to this turn


class Transcript:
    def __init__(self, backend: str):
        self.backend = backend
        self.turns: list[Turn] = []

    def add(self, turn: Turn) -> Turn:
        self.turns.append(turn)
        return turn

    def to_dict(self) -> dict:
        turns = sorted(self.turns, key=lambda t: t.start_s)
        return {"backend": self.backend, "turns": [_rounded(asdict(t)) for t in turns]}

    def write(self, path: Path) -> None:
        """Atomic replace, so a reader never sees a half-written file (and a failed write leaves the last one)."""
        write_text_atomic(path, json.dumps(self.to_dict(), indent=1))


def _rounded(value):
    if isinstance(value, float):
        return round(value, 3)
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value
