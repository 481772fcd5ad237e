"""The one key/value ring of every attention that streams: the training model's streaming attention
(`gesture.nn.attention`) and the step paths of the codec (`gesture.codec.step_transformer`) and the LM
(`gesture.lm.stepper`)."""

from __future__ import annotations

import torch

EMPTY_POSITION = -1


class RingKVCache:
    """Fixed-capacity key/value ring, (B, H, capacity, D) each; never grows. Position p lives in slot p % capacity.

    - `append(k, v)` writes T new entries at absolute positions `next_position, ...` (or from `start_position`,
      e.g. for a memory ring with its own clock) and returns the whole buffer with `positions` (capacity,) int64,
      where an empty slot holds -1. Slot order is not time order: attention must mask by the returned positions
      (see `gesture.nn.attention.attention_mask`).
    - `push(k, v)` writes one step at `next_position` and returns the filled slots. Pushed slots fill in order, so
      the filled ones are the first min(steps, capacity): a query that may see the whole window attends to them
      without a mask (softmax attention does not depend on the order of its keys). Its views are made once.
    """

    def __init__(
        self,
        batch_size: int,
        num_heads: int,
        head_dim: int,
        capacity: int,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"RingKVCache capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.keys = torch.zeros(batch_size, num_heads, capacity, head_dim, device=device, dtype=dtype)
        self.values = torch.zeros_like(self.keys)
        self.positions = torch.full((capacity,), EMPTY_POSITION, dtype=torch.long, device=device)
        self.next_position = 0
        self._slots = [(self.keys[:, :, s], self.values[:, :, s]) for s in range(capacity)]  # (B, H, D)
        self._filled = [(self.keys[:, :, :n], self.values[:, :, :n]) for n in range(1, capacity + 1)]  # (B, H, n, D)

    def reset(self) -> None:
        self.positions.fill_(EMPTY_POSITION)
        self.next_position = 0

    def push(self, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Write one step's k, v (B, H, D); return the keys and values of the filled slots, (B, H, n, D) each."""
        position = self.next_position
        slot = position % self.capacity
        keys, values = self._slots[slot]
        keys.copy_(k)
        values.copy_(v)
        self.positions[slot] = position
        self.next_position = position + 1
        return self._filled[min(position, self.capacity - 1)]

    def append(
        self, k: torch.Tensor, v: torch.Tensor, start_position: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Write k, v (B, H, T, D); return (keys, values, positions) of the whole ring."""
        steps = k.shape[2]
        if steps > self.capacity:
            raise ValueError(f"cannot append {steps} steps to a ring of capacity {self.capacity}")
        start = self.next_position if start_position is None else start_position
        slot = start % self.capacity
        first = min(steps, self.capacity - slot)  # entries before the ring wraps
        self.keys[:, :, slot : slot + first] = k[:, :, :first]
        self.values[:, :, slot : slot + first] = v[:, :, :first]
        if first == 1:
            self.positions[slot] = start
        else:
            self.positions[slot : slot + first] = torch.arange(start, start + first, device=self.positions.device)
        if first < steps:
            rest = steps - first
            self.keys[:, :, :rest] = k[:, :, first:]
            self.values[:, :, :rest] = v[:, :, first:]
            self.positions[:rest] = torch.arange(start + first, start + steps, device=self.positions.device)
        self.next_position = start + steps
        return self.keys, self.values, self.positions
