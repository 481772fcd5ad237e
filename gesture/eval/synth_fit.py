"""Fit the synthetic agent's micro-motion to real motion (calibration.json ``micro_motion``).

    python -m gesture.eval.synth_fit [--clip ../shared/data/beat2/2_scott_0_1_1] [--seeds 0 1 2 3 4] [--iterations 10]

The synthetic agent is driven by the clip's own speech and word timings (gesture.synth.recording). Per
joint of the torso, neck, head and arms, the fit matches three marginal statistics of the clip (never its frames):
its pose diversity (the mean angle of its local rotation from its mean, gesture.eval.realism), its median angular
speed (rad/s) and the share of its angular velocity's power at 2-8 Hz (gesture.eval.realism.fast_share). It starts
from the variance per local axis that the planned motion lacks (real - planned, floored at a quarter of the real
std), the cutoff at which noise of that size has the real median speed and a quick noise of INITIAL_FAST_RATIO, then
scales the noise (per joint), its cutoff and the quick noise's ratio multiplicatively from the measured synthetic
motion (mean over ``--seeds``), ``--iterations`` times (calibration.MicroNoise).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np

from ecas.core.body import COLLARS, ELBOWS, NECK_HEAD, PELVIS, SHOULDERS, SPINE, WRISTS
from ecas.core.paths import real_clip
from ecas.core.threads import limit_threads
from ecas.core.timing import MOTION_FPS
from gesture.body.rotation import axis_angle_to_matrix, matrix_to_axis_angle
from gesture.synth.calibration import CALIBRATION_JSON, MicroNoise, load_calibration, to_json
from gesture.synth.recording import motion_for_recording, recognised_words
from gesture.synth.tracks import lowpass_noise

MICRO_JOINTS = tuple(
    sorted((PELVIS, *SPINE, *NECK_HEAD, *COLLARS, *SHOULDERS, *ELBOWS, *WRISTS))
)  # the arms, the trunk
STD_FLOOR = 0.25  # of the real std: every joint keeps some micro-motion
MAX_STEP = 2.0  # largest multiplicative correction per iteration
PROBE_HZ = 1.0
INITIAL_FAST_RATIO = 0.3  # the quick noise's size, relative to the slow one's, before the fit
MAX_FAST_RATIO = 3.0
MAX_CUTOFF_HZ = 3.0  # faster noise is jitter, not motion (a joint whose planned motion is already too spread, the
# shoulders, would otherwise buy its median speed with it)
REAL_CLIP = real_clip()


def rotation_residuals(poses: np.ndarray) -> np.ndarray:
    """(T, J, 3) axis-angle -> (T, J, 3): log(mean^T R_t), each joint's rotation about its chordal mean."""
    rot = axis_angle_to_matrix(np.asarray(poses, np.float64))  # (T, J, 3, 3)
    u, _, vt = np.linalg.svd(rot.mean(0))  # (J, 3, 3): projection of the mean matrix onto SO(3)
    flip = np.ones(u.shape[:-1])  # (J, 3)
    flip[:, 2] = np.sign(np.linalg.det(u @ vt))
    mean = (u * flip[:, None, :]) @ vt
    return matrix_to_axis_angle(np.swapaxes(mean, -1, -2)[None] @ rot)


def joint_stats(poses: np.ndarray, fps: float = MOTION_FPS) -> tuple[np.ndarray, ...]:
    """(T, 55, 3) -> of MICRO_JOINTS: std per axis (J, 3), pose diversity (J,), median angular speed (J,) and the
    share of quick motion (J,; gesture.eval.realism.fast_share)."""
    from gesture.eval.realism import angular_speeds, fast_share, inner, pose_diversity, velocity_power

    poses = inner(poses[:, list(MICRO_JOINTS)])
    return (
        rotation_residuals(poses).std(0),
        pose_diversity(poses),
        np.median(angular_speeds(poses, fps), axis=0),
        fast_share(*velocity_power(poses, fps)),
    )


def noise_median_speed(std: np.ndarray, hz: float, n: int = 4000, fps: float = MOTION_FPS) -> float:
    """Median angular speed (rad/s) of a slow micro-motion noise alone (std (3,) rad, cutoff ``hz``)."""
    from gesture.eval.realism import angular_speeds

    offsets = lowpass_noise(np.random.default_rng(0), n, fps, hz, 3) * std[None]  # (n, 3)
    return float(np.median(angular_speeds(offsets[:, None], fps)))


def synthetic_stats(wav: Path, words, seeds, params) -> tuple[np.ndarray, ...]:
    """joint_stats of the synthetic agent driven by the recording, averaged over ``seeds``."""
    stats = [joint_stats(motion_for_recording(wav, seed=seed, words=words, micro=params)[1].poses) for seed in seeds]
    return tuple(np.mean([s[k] for s in stats], 0) for k in range(len(stats[0])))


def fit(
    clip: Path,
    seeds=(0, 1, 2),
    iterations: int = 3,
    words=None,
    log=print,
    keep: Mapping[int, MicroNoise] | None = None,
) -> dict[int, MicroNoise]:
    """Per joint of MICRO_JOINTS, its noise; ``words``: the clip's timed words (else recognised); ``keep``: joints
    held at the given noise throughout (the others are fitted with them in place)."""
    from gesture.eval.realism import load_clip

    wav = clip.with_suffix(".wav")
    real_std, real_div, real_med, real_fast = joint_stats(load_clip(clip.with_suffix(".npz")).poses)
    words = recognised_words(wav) if words is None else words
    keep = dict(keep or {})
    base_std = synthetic_stats(wav, words, seeds, {})[0]
    std = np.sqrt(np.maximum(real_std**2 - base_std**2, (STD_FLOOR * real_std) ** 2))  # (J, 3)
    hz = np.array([PROBE_HZ * real_med[k] / noise_median_speed(std[k], PROBE_HZ) for k in range(len(MICRO_JOINTS))])
    hz = np.minimum(hz, MAX_CUTOFF_HZ)
    fast = np.full(len(MICRO_JOINTS), INITIAL_FAST_RATIO)
    for it in range(iterations):
        params = {j: MicroNoise(std[k], float(hz[k]), float(fast[k])) for k, j in enumerate(MICRO_JOINTS)} | keep
        _, got_div, got_med, got_fast = synthetic_stats(wav, words, seeds, params)
        log(
            f"iteration {it}: diversity ratio {np.round(got_div / real_div, 2).tolist()}, "
            f"median speed ratio {np.round(got_med / real_med, 2).tolist()}, "
            f"quick share ratio {np.round(got_fast / real_fast, 2).tolist()}"
        )
        std = np.maximum(std * np.clip(real_div / got_div, 1 / MAX_STEP, MAX_STEP)[:, None], STD_FLOOR * real_std)
        hz = np.minimum(hz * np.clip(real_med / got_med, 1 / MAX_STEP, MAX_STEP), MAX_CUTOFF_HZ)
        fast = np.minimum(fast * np.clip(real_fast / got_fast, 1 / MAX_STEP, MAX_STEP), MAX_FAST_RATIO)
    return {j: MicroNoise(std[k], float(hz[k]), float(fast[k])) for k, j in enumerate(MICRO_JOINTS)} | keep


def main(argv=None) -> int:
    limit_threads()
    p = argparse.ArgumentParser(prog="ecas synth-fit", description=__doc__.splitlines()[0])
    p.add_argument("--clip", default=str(REAL_CLIP), help="the real clip without extension (.npz and .wav)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--iterations", type=int, default=10, help="the three statistics settle within 1-3 %% by 8")
    p.add_argument(
        "--joints",
        type=int,
        nargs="+",
        choices=MICRO_JOINTS,
        metavar="J",
        help="refit only these joints, holding the others at calibration.json's (default: all of "
        f"{list(MICRO_JOINTS)})",
    )
    p.add_argument("--out", default=str(CALIBRATION_JSON))
    args = p.parse_args(argv)
    clip = Path(args.clip)
    for suffix in (".npz", ".wav"):
        if not clip.with_suffix(suffix).is_file():
            print(f"error: {clip.with_suffix(suffix)}: not found", file=sys.stderr)
            return 2
    cal = load_calibration()
    held = [j for j in MICRO_JOINTS if args.joints and j not in args.joints]
    missing = [j for j in held if j not in cal.micro_motion]
    if missing:
        print(f"error: --joints: joints {missing} have no stored fit to hold; refit them too", file=sys.stderr)
        return 2
    fitted = fit(clip, tuple(args.seeds), args.iterations, keep={j: cal.micro_motion[j] for j in held})
    Path(args.out).write_text(json.dumps(to_json(replace(cal, micro_motion=fitted)), indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
