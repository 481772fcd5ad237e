"""The contract of a runtime layer: what it is given each step, what it returns, and what it is built from.

A layer is an object with `reset()` (a new session: back to the state it was built in) and
`step(value, context) -> value`, called once per 80 ms step in the order of the config's `gesture.layers` list:

- a motion layer (`stage = "motion"`) gets the step's decoded `Motion` and returns a new `Motion`;
- a token layer (`stage = "tokens"`) gets the LM's `Tokens` before the codecs decode them and returns new `Tokens`.

A layer never writes into the arrays it is given (the generator keeps the LM's tokens as its history) and owns its
state, allocated at construction: nothing in it grows with the session. It reads the step's `StepContext` and draws
random numbers only from streams it seeded itself from `LayerEnv.seed`, so a session replays exactly after
`reset()`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar, Literal, Protocol, runtime_checkable

import numpy as np

from ecas.core.body import CONTACT_JOINTS, NUM_EXPRESSIONS, NUM_JOINTS
from ecas.core.config import ConfigError
from ecas.core.timing import MOTION_FPS

SILENT_L2 = 0.5  # the idle gate's silence: the agent's last SILENT_WINDOW_SAMPLES have at most this L2 norm
SILENT_WINDOW_SAMPLES = 5760  # 3 steps at 24 kHz
# An agent frame counts as speech when its RMS is above the idle gate's silence as a per-sample RMS (the default of
# GestureGenerator's and the gesture section's speaking_rms).
SPEAKING_RMS = SILENT_L2 / np.sqrt(SILENT_WINDOW_SAMPLES)

Stage = Literal["motion", "tokens"]


@dataclass(frozen=True)
class Motion:
    """One step of decoded motion, F frames (2 in the generator)."""

    poses: np.ndarray  # (F, 55, 3) axis-angle, SMPL-X joint order
    trans: np.ndarray  # (F, 3) metres
    expressions: np.ndarray  # (F, 100) expression coefficients
    contacts: np.ndarray  # (F, 4) the decoded foot contacts of ecas.core.body.CONTACT_JOINTS (ankles, then feet)

    @classmethod
    def of(cls, poses=None, trans=None, expressions=None, contacts=None, frames: int | None = None) -> Motion:
        """A Motion from the parts given, the others zeros (tests and tools that run one layer)."""
        given = next((x for x in (poses, trans, expressions, contacts) if x is not None), None)
        frames = len(given) if frames is None else frames
        zeros = lambda *shape: np.zeros((frames, *shape), np.float32)
        return cls(
            zeros(NUM_JOINTS, 3) if poses is None else np.asarray(poses),
            zeros(3) if trans is None else np.asarray(trans),
            zeros(NUM_EXPRESSIONS) if expressions is None else np.asarray(expressions),
            zeros(len(CONTACT_JOINTS)) if contacts is None else np.asarray(contacts),
        )


@dataclass(frozen=True)
class Tokens:
    """One step of the LM's tokens as the codecs will decode them."""

    levels: np.ndarray  # (K,) int64, one token per level (upper, lower, face)
    idle: bool = False  # True once a token layer replaced LM tokens with recorded idle ones


def frame_rms(agent_pcm: np.ndarray | None, frames: int) -> np.ndarray:
    """(frames,) the RMS of each frame's share of one step of agent audio (zeros without audio)."""
    if agent_pcm is None or len(agent_pcm) < frames:
        return np.zeros(frames)
    usable = len(agent_pcm) // frames * frames
    return np.sqrt(np.mean(np.square(np.asarray(agent_pcm[:usable], np.float64).reshape(frames, -1)), axis=1))


@dataclass(frozen=True)
class StepContext:
    """What a layer may read about its step besides the motion."""

    step: int  # the step's index in the session, from 0
    agent_pcm: np.ndarray | None  # (STEP_SAMPLES,) float32 in [-1, 1]: the agent's audio of this step; None: silent
    frame_rms: np.ndarray  # (F,) the RMS of each frame's share of agent_pcm
    speaking: np.ndarray  # (F,) bool: the frame's RMS is above the generator's speaking_rms

    @classmethod
    def of(cls, agent_pcm: np.ndarray | None, frames: int, step: int = 0, speaking_rms: float = SPEAKING_RMS):
        rms = frame_rms(agent_pcm, frames)
        return cls(step, agent_pcm, rms, rms > speaking_rms)


@runtime_checkable
class MotionLayer(Protocol):
    stage: ClassVar[Stage]  # "motion"

    def reset(self) -> None: ...

    def step(self, motion: Motion, context: StepContext) -> Motion: ...


@runtime_checkable
class TokenLayer(Protocol):
    stage: ClassVar[Stage]  # "tokens"

    def reset(self) -> None: ...

    def step(self, tokens: Tokens, context: StepContext) -> Tokens: ...


Layer = MotionLayer | TokenLayer


@dataclass(frozen=True)
class LayerEnv:
    """What a layer's builder may read besides its options."""

    seed: int = 0  # the session seed: a layer seeds its own random streams from it
    fps: float = MOTION_FPS
    levels: Mapping[str, slice] = field(default_factory=dict)  # the LM's token levels per region (upper, lower, face)


class LayerOptionError(ConfigError):
    """A layer option's bad value; the message starts with the option's name within the layer ("hold_rad: ...").
    The registry prefixes the layer's place in the config (`gesture.layers[2].stabilizer.hold_rad: ...`)."""
