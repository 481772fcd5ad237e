"""Calibration of the synthetic agent from real BEAT2 motion (the clip 2_scott_0_1_1).

The generator must not need the clip at run time, so the numbers live in ``calibration.json`` beside this
file; ``python -m gesture.synth.calibration CLIP.npz`` recomputes them (a test checks they agree).

What is measured (at the clip's own frame rate; rotations averaged as quaternions):
- ``base_local_aa``: the mean local rotation of the torso, neck/head, collars and jaw, and of the root with its
  heading removed (the rest posture the agent returns to);
- ``relaxed_hand_aa``: the mean pose of the 30 finger joints (the "relaxed" hand shape);
- ``wrist_chest_m``: percentiles 5/50/95 of each wrist's position in the chest (spine3) frame, which bound the
  gesture space; the median is the hands' rest position;
- ``wrist_speed_mps``: the mean wrist speed, a reference for the synthetic motion's energy;
- ``micro_motion``: per joint of the torso, neck, head and arms, the low-passed rotation noise that the agent's
  joints carry on top of its planned motion (real speakers are never still; ``MicroNoise``). Fitted by
  ``python -m gesture.eval.synth_fit`` so that the synthetic agent, driven by the clip's own speech, matches the
  clip's per-joint rotation spread, median angular speed and share of quick motion.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from ecas.core.body import COLLARS, HAND_JOINTS, JAW_JOINT, NECK_HEAD, PELVIS, SPINE, WRISTS
from gesture.body.rotation import (
    axis_angle_to_matrix,
    axis_angle_to_quaternion,
    matrix_to_axis_angle,
    quaternion_to_axis_angle,
    rotation_about_y,
    yaw_of_matrix,
)
from gesture.body.skeleton import Skeleton, forward_kinematics_np

CALIBRATION_JSON = Path(__file__).with_name("calibration.json")
BASE_JOINTS = tuple(sorted((PELVIS, *SPINE, *NECK_HEAD, *COLLARS, JAW_JOINT)))  # (0, 3, 6, 9, 12, 13, 14, 15, 22)
CHEST_JOINT = SPINE[-1]
PERCENTILES = (5, 50, 95)


MICRO_FAST_HZ = 3.0  # the corner of each joint's quick micro-motion (MicroNoise.fast_ratio)


@dataclass(frozen=True)
class MicroNoise:
    """One joint's micro-motion, per local axis: a slow noise of ``std_rad`` low-passed at ``cutoff_hz`` plus a quick
    one of ``fast_ratio`` times that size low-passed at MICRO_FAST_HZ (both gesture.synth.tracks.lowpass_noise).

    Real joints move at every rate: a speaker's spine has a third of its angular velocity's power at 2-8 Hz, his
    wrists half. One noise fitted to the joint's spread and median speed leaves that band nearly empty."""

    std_rad: np.ndarray  # (3,)
    cutoff_hz: float
    fast_ratio: float = 0.0


@dataclass(frozen=True)
class Calibration:
    base_local_aa: dict[int, np.ndarray]  # joint -> (3,) axis-angle
    relaxed_hand_aa: np.ndarray  # (30, 3) joints 25..54
    wrist_chest_m: np.ndarray  # (2 sides L/R, 3 percentiles, 3 xyz) in the chest frame
    wrist_speed_mps: float
    micro_motion: dict[int, MicroNoise] = field(default_factory=dict)


def _mean_rotation(aa: np.ndarray) -> np.ndarray:
    """(T, 3) axis-angle -> (3,) the normalised mean quaternion (signs aligned to the first)."""
    q = axis_angle_to_quaternion(aa.astype(np.float64))  # (T, 4)
    q = np.where((q @ q[0])[:, None] < 0, -q, q)
    mean = q.mean(0)
    return quaternion_to_axis_angle(mean / np.linalg.norm(mean))


def calibrate(npz_path: Path | str) -> Calibration:
    with np.load(npz_path) as data:
        poses = data["poses"].reshape(-1, 55, 3).astype(np.float32)  # (T, 55, 3)
        trans = data["trans"].astype(np.float32)
        fps = float(data["mocap_frame_rate"])
    root = axis_angle_to_matrix(poses[:, 0].astype(np.float64))  # (T, 3, 3)
    unyawed = rotation_about_y(-yaw_of_matrix(root)) @ root
    base = {0: _mean_rotation(matrix_to_axis_angle(unyawed))}
    base.update({j: _mean_rotation(poses[:, j]) for j in BASE_JOINTS[1:]})
    hands = np.stack([_mean_rotation(poses[:, j]) for j in HAND_JOINTS])  # (30, 3)
    joints, transforms = forward_kinematics_np(Skeleton.default(), poses, trans)  # (T, 55, 3), (T, 55, 4, 4)
    chest_rot = transforms[:, CHEST_JOINT, :3, :3]  # (T, 3, 3)
    chest_pos = joints[:, CHEST_JOINT]
    wrists = []
    for j in WRISTS:
        local = np.einsum("tji,tj->ti", chest_rot, joints[:, j] - chest_pos)  # R^T (p - c), (T, 3)
        wrists.append(np.percentile(local, PERCENTILES, axis=0))  # (3, 3)
    speed = np.linalg.norm(np.diff(joints[:, list(WRISTS)], axis=0), axis=-1) * fps  # (T-1, 2)
    return Calibration(base, hands.astype(np.float64), np.stack(wrists), float(speed.mean()))


def to_json(cal: Calibration) -> dict:
    return {
        "base_local_aa": {str(j): np.round(v, 5).tolist() for j, v in cal.base_local_aa.items()},
        "relaxed_hand_aa": np.round(cal.relaxed_hand_aa, 5).tolist(),
        "wrist_chest_m": np.round(cal.wrist_chest_m, 5).tolist(),
        "wrist_speed_mps": round(cal.wrist_speed_mps, 5),
        "micro_motion": {
            str(j): {
                "std_rad": np.round(m.std_rad, 5).tolist(),
                "cutoff_hz": round(float(m.cutoff_hz), 4),
                "fast_ratio": round(float(m.fast_ratio), 4),
            }
            for j, m in sorted(cal.micro_motion.items())
        },
    }


def from_json(doc: dict) -> Calibration:
    return Calibration(
        base_local_aa={int(j): np.asarray(v, np.float64) for j, v in doc["base_local_aa"].items()},
        relaxed_hand_aa=np.asarray(doc["relaxed_hand_aa"], np.float64),
        wrist_chest_m=np.asarray(doc["wrist_chest_m"], np.float64),
        wrist_speed_mps=float(doc["wrist_speed_mps"]),
        micro_motion={
            int(j): MicroNoise(np.asarray(v["std_rad"], np.float64), float(v["cutoff_hz"]), float(v["fast_ratio"]))
            for j, v in doc.get("micro_motion", {}).items()
        },
    )


@lru_cache(maxsize=1)
def load_calibration() -> Calibration:
    """The stored calibration (``calibration.json``)."""
    return from_json(json.loads(CALIBRATION_JSON.read_text()))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="ecas calibrate", description="Recompute calibration.json from a BEAT2 npz.")
    parser.add_argument("npz", help="a BEAT2 SMPL-X npz, e.g. ../shared/data/beat2/2_scott_0_1_1.npz")
    parser.add_argument("--out", default=str(CALIBRATION_JSON))
    args = parser.parse_args(argv)
    fresh = replace(calibrate(args.npz), micro_motion=load_calibration().micro_motion)  # that one has its own fit
    Path(args.out).write_text(json.dumps(to_json(fresh), indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
