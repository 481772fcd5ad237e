"""What a stage's component sees of the run, and what it must provide: the contract between the stage runner
(`agent.stage`) and the model packages that plug into it."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from ecas.core.messages import Message


class StageFailed(RuntimeError):
    """Raised by a component's handler when no later message can succeed (e.g. its output cannot be written).

    The message is one line naming what failed, e.g. "cannot write out.mp4: [Errno 28] No space left on device".
    """


@dataclass(frozen=True)
class RunContext:
    """What a component may know about the run."""

    run_dir: Path
    live: bool
    seed: int
    session: str
    addresses: dict[str, str] = field(
        default_factory=dict
    )  # process -> its bus address (`ecas.core.bus.bus_addresses`)


class Component(Protocol):
    def handle(self, msg: Message) -> Sequence[Message]: ...

    def flush(self) -> Sequence[Message]: ...

    def close(self) -> None: ...


class ClockAware(Protocol):
    """Optional for a component that compares a step's `t_origin_ns` with its own clock (e.g. to drop late work).

    The stage runner calls it on START with the measured offset of the capturing stage's clock: the origin stage
    may run on another host (`run.spawn`), whose monotonic clock has another zero.
    """

    def set_origin_offset_ns(self, offset_ns: int) -> None:
        """`t_origin_ns + offset_ns` is the capture time on this process's clock."""


class Source(Protocol):
    """Blocks of user audio. `paced` sources (a microphone) deliver in real time by themselves."""

    paced: bool

    def next_block(self, timeout_s: float) -> tuple[np.ndarray, int | None] | None:
        """(pcm (1920,) float32, capture time of its last sample in monotonic ns or None); None when waiting."""

    @property
    def exhausted(self) -> bool: ...

    def close(self) -> None: ...
