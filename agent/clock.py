"""NTP-style clock offsets of the stage processes relative to the supervisor.

For a PING sent at t0 (supervisor clock), received at t1 and answered at t2 (stage clock), and the PONG
received at t3: offset = ((t1 - t0) + (t2 - t3)) / 2, round trip = (t3 - t0) - (t2 - t1). The sample with the
shortest round trip wins; its half round trip bounds the error. On one host every process reads the same
CLOCK_MONOTONIC and the offsets come out near zero; across hosts they make the stamps comparable.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class OffsetEstimate:
    offset_ns: int  # stage clock minus supervisor clock
    uncertainty_ns: int  # half the round trip of the best sample
    samples: int


class ClockSync:
    def __init__(self):
        self._best: dict[str, tuple[int, int]] = {}  # stage -> (round trip, offset)
        self._count: dict[str, int] = {}

    def add(self, stage: str, t0: int, t1: int, t2: int, t3: int) -> None:
        round_trip = (t3 - t0) - (t2 - t1)
        offset = ((t1 - t0) + (t2 - t3)) // 2
        self._count[stage] = self._count.get(stage, 0) + 1
        if stage not in self._best or round_trip < self._best[stage][0]:
            self._best[stage] = (round_trip, offset)

    def estimates(self) -> dict[str, OffsetEstimate]:
        return {
            stage: OffsetEstimate(offset, max(0, rtt) // 2, self._count[stage])
            for stage, (rtt, offset) in self._best.items()
        }

    def offsets_ns(self) -> dict[str, int]:
        """The offsets to subtract; one within its own uncertainty is taken as zero (e.g. one host's clock)."""
        return {stage: offset if abs(offset) > max(0, rtt) // 2 else 0 for stage, (rtt, offset) in self._best.items()}
