"""Streaming modules: a module owns a typed state object while it streams; offline when it has none.

Usage::

    with model.streaming(batch_size=1):       # every StreamingModule inside gets a fresh state
        for chunk in chunks:
            y = model(chunk)                   # same forward as offline; state carries across calls
        model.reset_streaming()                # back to the start of a stream, buffers kept

Nothing in a state grows with time: buffers are allocated once, in `_init_streaming_state`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

import torch
from torch import nn


@dataclass
class StreamingState:
    """Base of every streaming state. Subclasses add preallocated buffers and override `reset`."""

    batch_size: int

    def reset(self) -> None:
        """Return to the start of a stream, in place (no reallocation)."""


S = TypeVar("S", bound=StreamingState)


class StreamingModule(nn.Module, Generic[S]):
    """An nn.Module that can run step by step. Subclasses implement `_init_streaming_state`.

    `self.streaming_state` is None offline; inside `streaming(...)` it is the module's typed state.
    Starting, resetting and stopping a module does the same for every StreamingModule below it.
    """

    def __init__(self) -> None:
        super().__init__()
        self._streaming_state: S | None = None

    def _init_streaming_state(self, batch_size: int) -> S:
        return StreamingState(batch_size)  # type: ignore[return-value]

    @property
    def streaming_state(self) -> S | None:
        return self._streaming_state

    @property
    def is_streaming(self) -> bool:
        return self._streaming_state is not None

    def _streaming_modules(self) -> Iterator[StreamingModule]:
        return (m for m in self.modules() if isinstance(m, StreamingModule))

    def start_streaming(self, batch_size: int) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        for module in self._streaming_modules():
            module._streaming_state = module._init_streaming_state(batch_size)

    def reset_streaming(self) -> None:
        for module in self._streaming_modules():
            if module._streaming_state is None:
                raise RuntimeError(f"{type(module).__name__} is not streaming; call start_streaming first")
            module._streaming_state.reset()

    def stop_streaming(self) -> None:
        for module in self._streaming_modules():
            module._streaming_state = None

    @contextlib.contextmanager
    def streaming(self, batch_size: int) -> Iterator[None]:
        self.start_streaming(batch_size)
        try:
            yield
        finally:
            self.stop_streaming()

    def _param_device_dtype(self) -> tuple[torch.device, torch.dtype]:
        for p in self.parameters():
            return p.device, p.dtype
        return torch.device("cpu"), torch.get_default_dtype()
