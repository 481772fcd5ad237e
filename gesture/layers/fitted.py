"""The fitted parameters the micro-motion and face layers use, read from `fitted.json` beside this file.

They are the synthetic training data's own (its micro-motion fitted on the real BEAT2 clip, its blinks and the
avatar's expression patterns), written from `gesture.synth` by `python -m tests.test_layer_fits --write`;
tests/test_layer_fits.py checks that the data generator still produces the same values. The layers never import the
data generator.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS

FITTED_JSON = Path(__file__).with_name("fitted.json")


@dataclass(frozen=True)
class MicroNoise:
    """One joint's micro-motion, per local axis: a slow noise of `std_rad` low-passed at `cutoff_hz` plus a quick
    one of `fast_ratio` times that size low-passed at `MicroFit.fast_hz`."""

    std_rad: np.ndarray  # (3,)
    cutoff_hz: float
    fast_ratio: float = 0.0


@dataclass(frozen=True)
class MicroFit:
    joints: dict[int, MicroNoise]  # every joint with a fitted micro-motion
    layered_joints: tuple[int, ...]  # the joints whose micro-motion the data leaves out of what the codecs learn
    fast_hz: float  # the corner of every joint's quick noise
    listening_scale: float  # the micro-motion's size while the agent listens, relative to speaking
    envelope_gain: float  # the size is 1 - gain/2 .. 1 + gain/2 with the smoothed speech envelope
    envelope_smooth_s: float  # the envelope's one-pole time constant
    gate_hz: float  # the log-normal gates' noise cutoff
    gate_log_std: float  # a body part's gate: its log's std ...
    gate_max: float  # ... and its cap
    parts: tuple[tuple[int, ...], ...]  # joints sharing a gate: pelvis, torso and head; left arm; right arm
    own_gates: dict[int, float]  # joint -> its own gate's log std (replaces its part's gate)


@dataclass(frozen=True)
class FaceFit:
    blink_row: np.ndarray  # (100,) expression coefficients -> the avatar's blink activation
    brow_row: np.ndarray  # (100,) -> the avatar's brow-raise activation
    brow_psi: np.ndarray  # (100,) the expression of a unit brow raise
    blink_psi: np.ndarray  # (100,) the expression of a unit blink (blink_row . blink_psi = 1)
    blinks_per_minute: float  # the data's blink rate
    blink_refractory_s: float  # no blink starts within this long of the last
    blink_rise_s: tuple[float, float]  # uniform ranges of a blink's rise, hold and fall
    blink_hold_s: tuple[float, float]
    blink_fall_s: tuple[float, float]


def _pattern(coefficients: dict[str, float]) -> np.ndarray:
    psi = np.zeros(NUM_EXPRESSIONS)
    for index, value in coefficients.items():
        psi[int(index)] = value
    return psi


@cache
def _document() -> dict:
    return json.loads(FITTED_JSON.read_text())


@cache
def micro_fit() -> MicroFit:
    doc = _document()["micro_motion"]
    return MicroFit(
        joints={
            int(j): MicroNoise(np.asarray(m["std_rad"], np.float64), m["cutoff_hz"], m["fast_ratio"])
            for j, m in doc["joints"].items()
        },
        layered_joints=tuple(doc["layered_joints"]),
        fast_hz=doc["fast_hz"],
        listening_scale=doc["listening_scale"],
        envelope_gain=doc["envelope_gain"],
        envelope_smooth_s=doc["envelope_smooth_s"],
        gate_hz=doc["gate_hz"],
        gate_log_std=doc["gate_log_std"],
        gate_max=doc["gate_max"],
        parts=tuple(tuple(part) for part in doc["parts"]),
        own_gates={j: gate["log_std"] for gate in doc["own_gates"] for j in gate["joints"]},
    )


@cache
def face_fit() -> FaceFit:
    doc = _document()["face"]
    blink_row = _pattern(doc["blink_row"])
    return FaceFit(
        blink_row=blink_row,
        brow_row=_pattern(doc["brow_row"]),
        brow_psi=_pattern(doc["brow_psi"]),
        blink_psi=blink_row / (blink_row @ blink_row),
        blinks_per_minute=doc["blinks_per_minute"],
        blink_refractory_s=doc["blink_refractory_s"],
        blink_rise_s=tuple(doc["blink_rise_s"]),
        blink_hold_s=tuple(doc["blink_hold_s"]),
        blink_fall_s=tuple(doc["blink_fall_s"]),
    )
