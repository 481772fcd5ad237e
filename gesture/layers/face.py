"""The face layer on the decoded expressions (not in the reference): blinks topped up to a total rate, and brow
raises smoothed.

The face codec decodes blinks and brow raises of its own, at rates that follow the speech it hears, and many of its
brow raises are twitches that the training data never makes (measurements: docs/quality_history.md, "Runtime
layers").

Blinks: each frame, the decoded face's own blinks are counted as the realism report counts them (a rise of 0.5
above the 4 s running median, 0.3 s apart; here causally, over the last 4 s), their rate is tracked (over the
last half minute or so), and the layer starts blinks of the synthetic data's shape at the rate still missing: a
Poisson train with the data's refractory time after any blink, its own or the codec's.

Brows: the avatar's brow activation is low-passed (first order) and the difference put back along the brow
pattern, which moves no other shape of the avatar. The blink and brow patterns and the blinks' timing are the
data's (`gesture.layers.fitted`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS
from gesture.layers.base import LayerEnv, LayerOptionError, Motion, StepContext
from gesture.layers.fitted import face_fit
from gesture.layers.registry import register
from gesture.layers.signal import bump
from gesture.layers.stabilizer import smoothing_share

BLINK_HEIGHT = 0.5  # a decoded blink: its activation rises this far above the running median ...
BLINK_MIN_GAP_S = 0.3  # ... at least this long after the previous one (gesture.eval.realism.FACE_EVENTS["blink"])
BASELINE_S = 4.0  # the running median's span (gesture.eval.realism.FACE_BASELINE_S)
OWN_RATE_TIME_S = 30.0  # the decoded blinks' rate: their count over the time, both exponentially weighted ...
OWN_RATE_MIN_S = 10.0  # ... the time at least this (early in a session, a first blink is not yet a rate)


@dataclass(frozen=True)
class FaceOptions:
    # the total blink rate, the decoded face's own blinks included (0: none added); by default the data's
    blinks_per_minute: float = field(default_factory=lambda: face_fit().blinks_per_minute)
    brow_cutoff_hz: float = 0.0  # the brow activation's low-pass (0: as decoded)

    def __post_init__(self) -> None:
        if not 0 <= self.blinks_per_minute < 75:
            raise LayerOptionError(f"blinks_per_minute: must be in [0, 75), got {self.blinks_per_minute}")
        if self.brow_cutoff_hz < 0:
            raise LayerOptionError(f"brow_cutoff_hz: must be >= 0, got {self.brow_cutoff_hz}")


class BlinkFill:
    """`step(activation)` -> this frame's added blink closure in [0, 1], given the decoded face's blink activation;
    one call per frame, `reset(rng)` per session. `per_minute`: the total blink rate, the decoded face's own blinks
    included."""

    def __init__(self, per_minute: float, fps: float) -> None:
        self.fit = face_fit()
        refractory_s = self.fit.blink_refractory_s
        if not 0 < per_minute * refractory_s < 60:
            raise ValueError(f"blinks_per_minute: must be in (0, {60 / refractory_s:g}), got {per_minute}")
        self.target_hz, self.fps = per_minute / 60.0, fps
        self.decay = float(np.exp(-1.0 / (OWN_RATE_TIME_S * fps)))
        self.history = np.empty(int(BASELINE_S * fps) | 1)  # (L,) ring of recent activations

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.history[:] = np.nan
        self.frame = 0
        self.own_count = self.own_time_s = 0.0  # exponentially weighted
        self.last_own_s = self.last_blink_s = -np.inf
        self.rising = False
        self.blinks: list[tuple[float, float, float, float]] = []  # (centre, rise, hold, fall) still to finish

    def _own_blink(self, activation: float, t_s: float) -> bool:
        """Whether the decoded face starts a blink at this frame (its activation crossing the height)."""
        self.history[self.frame % len(self.history)] = activation
        above = activation - np.nanmedian(self.history) > BLINK_HEIGHT
        starts = above and not self.rising and t_s - self.last_own_s >= BLINK_MIN_GAP_S
        self.rising = above
        return starts

    def _fill_probability(self, t_s: float) -> float:
        """This frame's chance of a layer blink: the missing rate as a Poisson train after the refractory time."""
        missing_hz = self.target_hz - self.own_count / max(self.own_time_s, OWN_RATE_MIN_S)
        refractory_s = self.fit.blink_refractory_s
        if missing_hz <= 0 or t_s - self.last_blink_s < refractory_s:
            return 0.0
        return 1.0 / ((1.0 / missing_hz - refractory_s) * self.fps)

    def step(self, activation: float) -> float:
        t_s = self.frame / self.fps
        self.own_count *= self.decay
        self.own_time_s = self.own_time_s * self.decay + 1.0 / self.fps
        if self._own_blink(activation, t_s):
            self.own_count += 1.0
            self.last_own_s = self.last_blink_s = t_s
        if self.rng.random() < self._fill_probability(t_s):
            phases = (self.fit.blink_rise_s, self.fit.blink_hold_s, self.fit.blink_fall_s)
            rise, hold, fall = (self.rng.uniform(*r) for r in phases)
            self.blinks.append((t_s + rise, rise, hold, fall))
            self.last_blink_s = t_s
        self.frame += 1
        self.blinks = [b for b in self.blinks if t_s <= b[0] + b[2] + b[3]]
        return min(1.0, sum(float(bump(np.array([t_s]), *b)[0]) for b in self.blinks))


class FaceLayer:
    """A motion layer on the expressions: blinks topped up to `blinks_per_minute` (0: none added) and the brow
    activation low-passed at `brow_cutoff_hz` (0: as decoded) (`apply` on the expressions); `reset()` per session."""

    stage = "motion"

    def __init__(self, fps: float, seed: int = 0, blinks_per_minute: float = 0.0, brow_cutoff_hz: float = 0.0) -> None:
        if brow_cutoff_hz < 0:
            raise ValueError(f"brow_cutoff_hz: must be >= 0, got {brow_cutoff_hz}")
        self.seed = seed
        self.fit = face_fit()
        self.blinks = BlinkFill(blinks_per_minute, fps) if blinks_per_minute else None
        self.brow_share = float(smoothing_share(brow_cutoff_hz, fps)) if brow_cutoff_hz else 1.0
        self.reset()

    def reset(self) -> None:
        if self.blinks is not None:
            self.blinks.reset(np.random.default_rng([self.seed, 1]))
        self.brow: float | None = None  # the smoothed brow activation

    def _smooth_brow(self, activation: float) -> float:
        self.brow = activation if self.brow is None else self.brow + self.brow_share * (activation - self.brow)
        return self.brow

    def step(self, motion: Motion, context: StepContext) -> Motion:
        return replace(motion, expressions=self.apply(motion.expressions))

    def apply(self, expressions: np.ndarray) -> np.ndarray:
        """(F, 100) expression coefficients -> the same with the blinks and brows of the layer."""
        expressions = np.asarray(expressions)
        if expressions.ndim != 2 or expressions.shape[1] != NUM_EXPRESSIONS:
            raise ValueError(f"expressions: expected (frames, {NUM_EXPRESSIONS}), got {expressions.shape}")
        out = expressions.astype(np.float64)  # (F, 100)
        fit = self.fit
        brow = out @ fit.brow_row  # (F,)
        brow_change = np.array([self._smooth_brow(a) for a in brow]) - brow
        closure = np.zeros(len(out))
        if self.blinks is not None:
            closure = np.array([self.blinks.step(a) for a in out @ fit.blink_row])  # (F,)
        out += brow_change[:, None] * fit.brow_psi[None] + closure[:, None] * fit.blink_psi[None]
        return out.astype(expressions.dtype)


@register("face", FaceOptions)
def build(options: FaceOptions, env: LayerEnv) -> FaceLayer:
    return FaceLayer(env.fps, env.seed, options.blinks_per_minute, options.brow_cutoff_hz)
