"""Realism report: motion generated for real speech against the real speaker's motion on that speech.

    ecas realism --json [--seed N] [--out DIR] [--motion DIR/motion.npz] [--synthetic NPZ] [--no-video]
        [--config YAML] [--set KEY=VALUE ...]   (passed to launch.py, e.g. a candidate agent or other checkpoints)
        [--clip PATH/TAKE [--wav WAV]]   (another real take: TAKE.npz, and its speech TAKE.wav or WAV)

The real BEAT2 clip's speech (``../shared/data/beat2/2_scott_0_1_1.wav``) is spoken by the ``playback`` backend
(``launch.py --speak WAV --headless --seed N --report DIR``, which writes the agent's motion to DIR/motion.npz;
``--motion`` reuses one) and compared with the real motion of that clip. Two references are measured the same
way, so the report is seen to discriminate:

- ``generated_codecs_only``: the same agent without its runtime layers (``gesture.layers=[]``): what its LM and
  codecs alone carry; not measured with ``--motion``;
- ``synthetic_gt``: the synthetic generator (gesture.synth) driven by the clip's own audio and word timings;
- ``baseline``: the clip's mean pose held still plus smooth noise (``BASELINE_NOISE_RAD``);
- ``real_through_codecs``: the real clip encoded and decoded by the agent's codecs (``--codecs``, else the config's
  ``gesture.codec_checkpoints``): the ceiling of what an agent speaking through those codecs can reach.

And the speaker against himself (``real_halves``): the clip's second half measured against its first, how far one
real speaker varies within one take (``speaker_against_himself``).

Measures (all at 25 fps, ``EDGE_S`` dropped at each end):
- per joint group (``JOINT_GROUPS``): angular speed of the local rotations (rad/s; the angle of R_t^T R_t+1 times
  the frame rate), its median and 90th percentile, the fraction of still frames (< ``STILL_RAD_S``), and pose
  diversity (the mean angle between a frame's rotation and the joint's mean rotation, rad);
- L1div, BeatAlign and the kinetic FGD by the reference protocol (gesture.eval.scores.evaluate_motion);
- gesture strokes per minute (peaks of wrist speed in the body frame, ``STROKE_*``) and the distribution of hand
  height (wrist above the pelvis in the body frame: percentiles, given as differences from the real clip's in
  metres, and the overlap of the two histograms, 1 = the same distribution), and the share of the wrists' velocity
  power in the body frame at ``FAST_BAND_HZ`` (``hands.quick_share``: how smoothly the hands travel; a speaker's
  joints move quickly together so that his hands' paths stay smooth, which noise drawn per joint does not);
- the feet: the fraction of frames an ankle is planted (moving over the floor slower than ``PLANTED_MPS``), the
  90th percentile of its speed, its steps per minute (``STEP_*``), and how far the pelvis travels over the floor in
  a second (median; the real speaker paces);
- blinks, brow raises and smiles per minute (events of the avatar's expression activations, ``FACE_EVENTS``);
- per joint group, the share of its angular velocity's power at ``FAST_BAND_HZ`` (``spectra``: how much of its
  motion is quick small movement rather than slow drift; the real speaker's spine has about a third there);
- the chest and the head in space (``world``, ``WORLD_PARTS``): the angular speed and acceleration of their world
  rotations. A speaker's spine and neck counter the turns beneath them (gesture.layers.reflex), so his head moves more
  steadily in space than its joints' local speeds suggest.

Every scalar is also given as a ratio to the real clip's. ``--out`` gets ``realism.json``, ``speeds.png`` (the
speed distributions, real against generated) and ``side_by_side.mp4`` (the real clip and the agent speaking the
same audio, both rendered as by ``render.play``).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import binary_closing, gaussian_filter1d, label, median_filter
from scipy.signal import find_peaks

from ecas.core.body import ANKLES, COLLARS, ELBOWS, NECK_HEAD, PELVIS, SHOULDERS, SPINE, WRISTS
from ecas.core.errors import DataError
from ecas.core.paths import CHECKPOINTS_DIR, DEFAULT_CONFIG, data_root, real_clip
from ecas.core.threads import limit_threads
from ecas.core.timing import MOTION_FPS
from gesture.body.motion import canonicalize
from gesture.body.rotation import (
    axis_angle_to_matrix,
    axis_angle_to_quaternion,
    matrix_to_axis_angle_np,
    quaternion_to_axis_angle,
)
from gesture.body.skeleton import Skeleton, forward_kinematics_np
from gesture.eval import metrics as M

SHARED_BEAT2 = data_root() / "beat2"
REAL_CLIP = real_clip()
MEAN_SPEED_NPY = SHARED_BEAT2 / "mean_vel_smplxflame_30.npy"
DEFAULT_APP_CONFIG = DEFAULT_CONFIG

JOINT_GROUPS = {
    "wrists": WRISTS,
    "elbows": ELBOWS,
    "shoulders": SHOULDERS,
    "collars": COLLARS,
    "neck_head": NECK_HEAD,
    "spine": SPINE,
}
WITHOUT_LAYERS = "gesture.layers=[]"  # the agent's LM and codecs alone: an empty list of runtime layers
GOAL_GROUPS = ("wrists", "elbows", "neck_head", "spine")  # the realism goals name these four ...
GROUP_GOAL_RANGE = (0.67, 1.5)  # ... and this range for every ratio of theirs
STILL_RAD_S = 0.2
FAST_BAND_HZ = (2.0, 8.0)
WORLD_PARTS = {"chest": (PELVIS, *SPINE), "head": (PELVIS, *SPINE, *NECK_HEAD)}  # root-to-part chains measured in space
EDGE_S = 2.0
PLANTED_MPS = 0.02  # an ankle moving slower than this over the floor is planted
STEP_MPS, STEP_MIN_M, STEP_SMOOTH_FRAMES = 0.1, 0.03, 1.0  # a step: an ankle faster than this, ending this far away
STROKE_SPEED_MPS = 0.35  # a stroke: a wrist speed peak at least this fast ...
STROKE_PROMINENCE_MPS = 0.2  # ... standing out this much from its surroundings ...
STROKE_MIN_GAP_S = 0.25  # ... and this far from the previous one (per wrist)
HEIGHT_BINS_M = np.linspace(-0.4, 0.6, 41)
FACE_EVENTS = {  # shape: (height above its 4 s running median, minimum spacing s) of an event's peak
    "blink": (0.5, 0.3),
    "brow_raise": (0.25, 0.6),
    "smile": (0.25, 1.0),
}
FACE_BASELINE_S = 4.0
BASELINE_NOISE_RAD = 0.02
BASELINE_NOISE_HZ = 2.0


# ---------------------------------------------------------------- motion at 25 fps


def load_clip(path: Path | str) -> M.MotionClip:
    """A motion file at 25 fps with the heading of its first frame removed."""
    return canonical(M.load_motion_clip(path).at_fps(MOTION_FPS))


def canonical(clip: M.MotionClip) -> M.MotionClip:
    poses, trans = canonicalize(clip.poses, clip.trans)
    return replace(clip, poses=poses, trans=trans)


def cut(clip: M.MotionClip, n_frames: int) -> M.MotionClip:
    return replace(
        clip, poses=clip.poses[:n_frames], trans=clip.trans[:n_frames], expressions=clip.expressions[:n_frames]
    )


def inner(x: np.ndarray, fps: float = MOTION_FPS) -> np.ndarray:
    edge = int(EDGE_S * fps)
    if len(x) <= 2 * edge + 2:
        raise ValueError(f"realism: a clip of {len(x)} frames is too short to drop {EDGE_S} s at each end")
    return x[edge : len(x) - edge]


# ---------------------------------------------------------------- joint groups


def frame_to_frame(poses: np.ndarray) -> np.ndarray:
    """(T, J, 3) axis-angle -> (T-1, J, 3, 3): each joint's local rotation from one frame to the next, R_t^T R_t+1."""
    rot = axis_angle_to_matrix(np.asarray(poses, np.float64))  # (T, J, 3, 3)
    return np.swapaxes(rot[:-1], -1, -2) @ rot[1:]


def angular_speeds(poses: np.ndarray, fps: float) -> np.ndarray:
    """(T, J, 3) axis-angle -> (T-1, J) rad/s: the angle of each joint's rotation from one frame to the next."""
    cos = (np.trace(frame_to_frame(poses), axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0)) * fps


def pose_diversity(poses: np.ndarray) -> np.ndarray:
    """(T, J, 3) -> (J,) mean angle (rad) between each frame's rotation and the joint's mean rotation."""
    q = axis_angle_to_quaternion(np.asarray(poses, np.float64))  # (T, J, 4)
    q = np.where((q * q[:1]).sum(-1, keepdims=True) < 0, -q, q)
    mean = q.mean(0)
    mean /= np.linalg.norm(mean, axis=-1, keepdims=True)
    dot = np.abs((q * mean[None]).sum(-1))  # (T, J)
    return (2 * np.arccos(np.clip(dot, 0.0, 1.0))).mean(0)


def group_stats(poses: np.ndarray, fps: float = MOTION_FPS) -> dict:
    """Per joint group: angular-speed median and p90 (rad/s), still fraction, pose diversity (rad)."""
    speeds = angular_speeds(poses, fps)  # (T-1, 55)
    diversity = pose_diversity(poses)
    out = {}
    for name, joints in JOINT_GROUPS.items():
        s = speeds[:, list(joints)].reshape(-1)
        out[name] = {
            "speed_median": float(np.median(s)),
            "speed_p90": float(np.percentile(s, 90)),
            "still_fraction": float((s < STILL_RAD_S).mean()),
            "diversity": float(diversity[list(joints)].mean()),
        }
    return out


def velocity_power(poses: np.ndarray, fps: float = MOTION_FPS) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, 3) axis-angle -> frequencies (F,) in Hz and (F, J) the power spectrum of each joint's angular velocity
    (local frame, summed over its axes)."""
    velocity = matrix_to_axis_angle_np(frame_to_frame(poses)) * fps  # (T-1, J, 3) rad/s
    power = np.square(np.abs(np.fft.rfft(velocity - velocity.mean(0), axis=0))).sum(-1)  # (F, J)
    return np.fft.rfftfreq(len(velocity), 1.0 / fps), power


def fast_share(hz: np.ndarray, power: np.ndarray) -> np.ndarray:
    """(F,), (F, ...) -> (...) the share of the power within ``FAST_BAND_HZ``."""
    fast = (hz >= FAST_BAND_HZ[0]) & (hz < FAST_BAND_HZ[1])
    return power[fast].sum(0) / np.maximum(power.sum(0), 1e-12)


def fast_power_shares(poses: np.ndarray, fps: float = MOTION_FPS) -> dict:
    """Per joint group: the share of its angular velocity's power (summed over its joints) within ``FAST_BAND_HZ``."""
    hz, power = velocity_power(poses, fps)
    return {
        name: {"fast_power_share": float(fast_share(hz, power[:, list(joints)].sum(1)))}
        for name, joints in JOINT_GROUPS.items()
    }


def world_rotations(poses: np.ndarray, chain: Sequence[int]) -> np.ndarray:
    """(T, J, 3) axis-angle -> (T, 3, 3): the world rotation of the last joint of ``chain`` (from the root down)."""
    from gesture.layers.reflex import chain_world

    local = axis_angle_to_matrix(np.asarray(poses, np.float64))  # (T, J, 3, 3)
    return chain_world(local, np.broadcast_to(np.eye(3), local[:, 0].shape), tuple(chain))


def world_stats(poses: np.ndarray, fps: float = MOTION_FPS) -> dict:
    """Per body part of ``WORLD_PARTS``: its world rotation's angular speed (median, p90; rad/s) and angular
    acceleration (median, p90; rad/s^2), how steadily it moves in space rather than against its parent."""
    out = {}
    for name, chain in WORLD_PARTS.items():
        world = world_rotations(poses, chain)  # (T, 3, 3)
        step = matrix_to_axis_angle_np(np.swapaxes(world[:-1], -1, -2) @ world[1:]) * fps  # (T-1, 3) own frame
        velocity = np.einsum("tij,tj->ti", world[:-1], step)  # (T-1, 3) rad/s in the world frame
        speed = np.linalg.norm(velocity, axis=-1)
        accel = np.linalg.norm(np.diff(velocity, axis=0), axis=-1) * fps
        out[name] = {
            "speed_median": float(np.median(speed)),
            "speed_p90": float(np.percentile(speed, 90)),
            "accel_median": float(np.median(accel)),
            "accel_p90": float(np.percentile(accel, 90)),
        }
    return out


def group_speed_samples(poses: np.ndarray, fps: float = MOTION_FPS) -> dict[str, np.ndarray]:
    speeds = angular_speeds(poses, fps)
    return {name: speeds[:, list(joints)].reshape(-1) for name, joints in JOINT_GROUPS.items()}


# ---------------------------------------------------------------- hands


def body_frame_joints(poses: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """(T, 55, 3) joint positions with the root rotation and translation removed (the body's own frame)."""
    local = np.array(poses, np.float32, copy=True)
    local[:, 0] = 0.0
    joints, _ = forward_kinematics_np(skeleton, local, np.zeros((len(local), 3), np.float32))
    return joints


def stroke_times_s(wrist: np.ndarray, fps: float = MOTION_FPS) -> np.ndarray:
    """(T, 3) wrist positions -> times (s) of its strokes: prominent peaks of its (lightly smoothed) speed."""
    speed = np.linalg.norm(np.gradient(gaussian_filter1d(wrist, 1.0, axis=0), axis=0), axis=-1) * fps  # (T,)
    peaks, _ = find_peaks(
        speed, height=STROKE_SPEED_MPS, prominence=STROKE_PROMINENCE_MPS, distance=max(1, int(STROKE_MIN_GAP_S * fps))
    )
    return peaks / fps


def position_fast_share(points: np.ndarray, fps: float = MOTION_FPS) -> float:
    """(T, K, 3) positions -> the share of their velocity's power (summed over points and axes) within
    ``FAST_BAND_HZ``."""
    velocity = np.diff(points, axis=0) * fps  # (T-1, K, 3) m/s
    power = np.square(np.abs(np.fft.rfft(velocity - velocity.mean(0), axis=0))).sum((1, 2))  # (F,)
    return float(fast_share(np.fft.rfftfreq(len(velocity), 1.0 / fps), power))


def hand_stats(joints: np.ndarray, fps: float = MOTION_FPS) -> dict:
    minutes = len(joints) / fps / 60.0
    strokes = sum(len(stroke_times_s(joints[:, w], fps)) for w in WRISTS)
    height = (joints[:, list(WRISTS), 1] - joints[:, PELVIS : PELVIS + 1, 1]).reshape(-1)  # (2T,) metres
    p10, p50, p90 = np.percentile(height, (10, 50, 90))
    return {
        "strokes_per_minute": strokes / minutes,
        "hand_height_p10_m": float(p10),
        "hand_height_median_m": float(p50),
        "hand_height_p90_m": float(p90),
        "quick_share": position_fast_share(joints[:, list(WRISTS)], fps),
    }


def step_count(ankle_xz: np.ndarray, fps: float = MOTION_FPS) -> int:
    """(T, 2) one ankle's floor position -> its steps: spans moving faster than ``STEP_MPS`` (smoothed over
    ``STEP_SMOOTH_FRAMES``; gaps of a frame closed) that end at least ``STEP_MIN_M`` from where they began."""
    speed = gaussian_filter1d(np.linalg.norm(np.diff(ankle_xz, axis=0), axis=-1) * fps, STEP_SMOOTH_FRAMES)
    moving, _ = label(binary_closing(speed > STEP_MPS, np.ones(3)))
    spans = [np.flatnonzero(moving == k) for k in range(1, moving.max() + 1)]
    return sum(np.linalg.norm(ankle_xz[span[-1] + 1] - ankle_xz[span[0]]) >= STEP_MIN_M for span in spans)


def feet_stats(poses: np.ndarray, trans: np.ndarray, skeleton: Skeleton, fps: float = MOTION_FPS) -> dict:
    """The ankles' horizontal speed in the world (m/s): the fraction of frames they are planted, and its 90th
    percentile (steps); steps per minute per ankle; how far the pelvis gets over the floor in one second (median,
    m/s)."""
    joints, _ = forward_kinematics_np(skeleton, np.asarray(poses, np.float32), np.asarray(trans, np.float32))
    floor = joints[..., [0, 2]]  # (T, J, 2)
    speed = np.linalg.norm(np.diff(floor[:, list(ANKLES)], axis=0), axis=-1).reshape(-1) * fps
    minutes = len(joints) / fps / 60
    second = int(round(fps))
    travel = np.linalg.norm(floor[second:, PELVIS] - floor[:-second, PELVIS], axis=-1)
    return {
        "ankles_planted_fraction": float((speed < PLANTED_MPS).mean()),
        "ankle_speed_p90": float(np.percentile(speed, 90)),
        "steps_per_minute": float(np.mean([step_count(floor[:, a], fps) for a in ANKLES]) / minutes),
        "pelvis_travel_mps": float(np.median(travel)),
    }


def height_histogram(joints: np.ndarray) -> np.ndarray:
    height = (joints[:, list(WRISTS), 1] - joints[:, PELVIS : PELVIS + 1, 1]).reshape(-1)
    hist, _ = np.histogram(np.clip(height, HEIGHT_BINS_M[0], HEIGHT_BINS_M[-1]), HEIGHT_BINS_M)
    return hist / max(hist.sum(), 1)


# ---------------------------------------------------------------- face


def face_activations(expressions: np.ndarray) -> dict[str, np.ndarray]:
    """(T, 100) FLAME psi -> the avatar's activations of the shapes in FACE_EVENTS (render.avatar's map)."""
    from render.expressions import EXPRESSION_MAP, SEMANTIC_SHAPES

    return {name: expressions @ EXPRESSION_MAP[SEMANTIC_SHAPES.index(name)] for name in FACE_EVENTS}


def face_event_times_s(activation: np.ndarray, height: float, min_gap_s: float, fps: float = MOTION_FPS) -> np.ndarray:
    base = median_filter(activation, size=int(FACE_BASELINE_S * fps) | 1, mode="nearest")
    peaks, _ = find_peaks(activation - base, height=height, distance=max(1, int(min_gap_s * fps)))
    return peaks / fps


def face_stats(expressions: np.ndarray, fps: float = MOTION_FPS) -> dict:
    minutes = len(expressions) / fps / 60.0
    acts = face_activations(np.asarray(expressions, np.float64))
    return {
        f"{name}s_per_minute": len(face_event_times_s(acts[name], *FACE_EVENTS[name], fps)) / minutes
        for name in FACE_EVENTS
    }


# ---------------------------------------------------------------- one motion against the real clip


def describe(clip: M.MotionClip, skeleton: Skeleton) -> dict:
    """Everything that does not need the real clip: groups, hands, feet, face (inner part of the clip)."""
    poses = inner(clip.poses)
    joints = body_frame_joints(poses, skeleton)
    return {
        "groups": group_stats(poses),
        "hands": hand_stats(joints),
        "feet": feet_stats(poses, inner(clip.trans), skeleton),
        "face": face_stats(inner(clip.expressions)),
        "spectra": fast_power_shares(poses),
        "world": world_stats(poses),
    }


def protocol_metrics(clip: M.MotionClip, real: M.MotionClip, speech, mean_speed: np.ndarray) -> dict:
    """L1div, BeatAlign and the kinetic FGD of ``clip`` and of the real clip (gesture.eval.metrics' reference protocol);
    ``speech``: the clip's speech (``gesture.eval.metrics.load_speech``)."""
    from gesture.eval.fgd import KineticGeometricEncoder, fgd

    pair = M.prepare_pair(clip, real)
    onsets = M.beat_align_onsets_s(speech, len(pair.gt_joints))
    return {
        "l1div": M.l1_div(pair.pred_joints),
        "beat_align": M.beat_align(pair.pred_joints, onsets, mean_speed),
        "fgd_kinetic": fgd(KineticGeometricEncoder(), pair.pred_poses, pair.pred_joints, pair.gt_poses, pair.gt_joints),
        "real_l1div": M.l1_div(pair.gt_joints),
        "real_beat_align": M.beat_align(pair.gt_joints, onsets, mean_speed),
    }


def _ratio(value: float, reference: float) -> float | None:
    return None if reference == 0 or not math.isfinite(reference) else value / reference


def ratios(stats: dict, real: dict) -> dict:
    """The same nested layout with every scalar divided by the real clip's; positions (``*_m``, which may be near
    zero) are given as differences instead, under ``<key>_minus_real``."""
    out = {}
    for key, value in stats.items():
        if isinstance(value, dict):
            out[key] = ratios(value, real[key])
        elif key.endswith("_m"):
            out[f"{key}_minus_real"] = float(value) - float(real[key])
        else:
            out[key] = _ratio(float(value), float(real[key]))
    return out


def goal_check(entry: dict, real_beat_align: float) -> dict:
    """Issue 18's goals for the agent: group ratios in 0.67-1.5, L1div within 25 %, BeatAlign >= real - 0.15."""
    r = entry["ratios"]["groups"]
    group_ok = all(GROUP_GOAL_RANGE[0] <= r[g][k] <= GROUP_GOAL_RANGE[1] for g in GOAL_GROUPS for k in r[g])
    calib_ok = all(0.8 <= v <= 1.25 for g in GOAL_GROUPS for v in r[g].values())
    return {
        "groups_within_0.67_1.5": group_ok,
        "groups_within_0.8_1.25": calib_ok,
        "l1div_within_25pct": abs(entry["ratios"]["l1div"] - 1) <= 0.25,
        "l1div_within_15pct": abs(entry["ratios"]["l1div"] - 1) <= 0.15,
        "beat_align_within_0.15": entry["protocol"]["beat_align"] >= real_beat_align - 0.15,
    }


# ---------------------------------------------------------------- the three motions


def synthetic_reference(wav: Path, n_frames: int, seed: int, words=None) -> M.MotionClip:
    from gesture.synth.recording import motion_for_recording

    _, motion = motion_for_recording(wav, seed=seed, words=words)
    return cut(canonical(M.MotionClip(motion.poses, motion.trans, motion.expressions, MOTION_FPS)), n_frames)


def through_codecs(clip: M.MotionClip, codec_dir: Path) -> M.MotionClip:
    """``clip`` encoded and decoded by the codecs in ``codec_dir``: the most of it that the agent's tokens can carry."""
    from gesture.body.regions import features_to_motion, motion_to_features
    from gesture.codec.evaluation import reconstruct
    from gesture.lm.codecs import REGIONS, load_codecs

    codecs = load_codecs(codec_dir)
    features = motion_to_features(clip.poses, clip.trans, clip.expressions, MOTION_FPS)  # region -> (T, F)
    with torch.no_grad():
        recon = {r: reconstruct(codecs[r], torch.from_numpy(features[r])).numpy() for r in REGIONS}
    poses, trans, expressions = features_to_motion(recon["upper"], recon["lower"], recon["face"])
    return canonical(M.MotionClip(poses, trans, expressions, MOTION_FPS))


def clip_words(wav: Path, cache: Path) -> list:
    """The recording's recognised words (gesture.synth.recording), kept in ``cache`` (JSON) for re-runs."""
    from gesture.synth.recording import TimedWord, recognised_words

    if cache.is_file():
        return [TimedWord(**w) for w in json.loads(cache.read_text())]
    words = recognised_words(wav)
    cache.write_text(json.dumps([vars(w) for w in words]))
    return words


def baseline_reference(real: M.MotionClip, seed: int) -> M.MotionClip:
    """The real clip's mean pose, held, plus smooth noise of BASELINE_NOISE_RAD on every joint axis."""
    q = axis_angle_to_quaternion(real.poses.astype(np.float64))  # (T, 55, 4)
    q = np.where((q * q[:1]).sum(-1, keepdims=True) < 0, -q, q)
    mean = q.mean(0)
    mean_aa = quaternion_to_axis_angle(mean / np.linalg.norm(mean, axis=-1, keepdims=True))  # (55, 3)
    n = len(real.poses)
    rng = np.random.default_rng(seed)
    sigma = MOTION_FPS / (2 * np.pi * BASELINE_NOISE_HZ)
    noise = gaussian_filter1d(rng.standard_normal((n, 55 * 3)), sigma, axis=0)
    noise *= BASELINE_NOISE_RAD / noise.std(0, keepdims=True)
    poses = mean_aa[None] + noise.reshape(n, 55, 3)
    trans = np.repeat(real.trans.mean(0, keepdims=True), n, 0)
    expressions = np.repeat(real.expressions.mean(0, keepdims=True), n, 0)
    return M.MotionClip(poses.astype(np.float32), trans.astype(np.float32), expressions.astype(np.float32), MOTION_FPS)


def speak_clip(wav: Path, seed: int, report_dir: Path, config: Path, overrides: Sequence[str] = ()) -> Path:
    """Run the agent of the app ``config`` on the recording with the playback backend (``overrides``: launch.py
    ``--set`` options); returns its motion.npz."""
    report_dir.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        "-m",
        "ecas.launch",
        "--config",
        str(config),
        "--speak",
        str(wav),
        "--headless",
        "--seed",
        str(seed),
        "--report",
        str(report_dir),
    ] + [arg for item in overrides for arg in ("--set", item)]
    with open(report_dir / "launch.out", "w") as log:
        subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, check=True)
    return report_dir / "motion.npz"


def config_codecs(config: Path, overrides: Sequence[str] = ()) -> Path:
    """The codec directory of the app ``config`` with ``--set`` ``overrides``."""
    from ecas.core.config import apply_override, build_dataclass, load_yaml, parse_override
    from gesture.config import GestureConfig

    tree = load_yaml(config)
    for text in overrides:
        apply_override(tree, *parse_override(text))
    codecs = build_dataclass(GestureConfig, tree.get("gesture"), "gesture").codec_checkpoints
    return codecs if codecs is not None else CHECKPOINTS_DIR / "codecs"


def halves(clip: M.MotionClip) -> tuple[M.MotionClip, M.MotionClip]:
    """The clip's first and second halves."""
    n = len(clip.poses) // 2
    return tuple(
        M.MotionClip(clip.poses[part], clip.trans[part], clip.expressions[part], clip.fps)
        for part in (slice(0, n), slice(n, 2 * n))
    )


def speaker_against_himself(real: M.MotionClip, skeleton: Skeleton) -> dict:
    """The real clip's second half measured against its first as an agent is against the real clip (``describe``'s
    measures as ratios; no protocol metrics): how much the speaker himself varies within one take, and which of the
    goal groups' ratios that alone puts outside GROUP_GOAL_RANGE."""
    first, second = halves(real)
    half_ratios = ratios(describe(second, skeleton), describe(first, skeleton))
    low, high = GROUP_GOAL_RANGE
    outside = [
        f"{group}.{key}"
        for group in GOAL_GROUPS
        for key, value in half_ratios["groups"][group].items()
        if not low <= value <= high
    ]
    return {"seconds_each": len(first.poses) / first.fps, "ratios": half_ratios, "goal_ratios_outside": outside}


def build_report(
    real: M.MotionClip, motions: dict[str, M.MotionClip], speech, mean_speed: np.ndarray, skeleton: Skeleton
) -> dict:
    real_desc = describe(real, skeleton)
    report: dict = {"real": dict(real_desc, protocol={}), "real_halves": speaker_against_himself(real, skeleton)}
    for name, clip in motions.items():
        desc = describe(clip, skeleton)
        protocol = protocol_metrics(clip, real, speech, mean_speed)
        report["real"]["protocol"] = {"l1div": protocol["real_l1div"], "beat_align": protocol["real_beat_align"]}
        entry = dict(desc, protocol={k: protocol[k] for k in ("l1div", "beat_align", "fgd_kinetic")})
        entry["ratios"] = ratios(
            {k: desc[k] for k in ("groups", "hands", "feet", "face", "spectra", "world")}, real_desc
        )
        entry["ratios"]["l1div"] = protocol["l1div"] / protocol["real_l1div"]
        entry["beat_align_minus_real"] = protocol["beat_align"] - protocol["real_beat_align"]
        entry["hand_height_overlap"] = float(
            np.minimum(
                height_histogram(body_frame_joints(inner(clip.poses), skeleton)),
                height_histogram(body_frame_joints(inner(real.poses), skeleton)),
            ).sum()
        )
        entry["goals"] = goal_check(entry, protocol["real_beat_align"])
        report[name] = entry
    return report


# ---------------------------------------------------------------- outputs


def plot_speeds(real: M.MotionClip, motions: dict[str, M.MotionClip], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = {"real": group_speed_samples(inner(real.poses))}
    samples.update({name: group_speed_samples(inner(clip.poses)) for name, clip in motions.items()})
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    bins = np.logspace(-2.5, 1.3, 50)
    styles = {
        "real": ("k", 2.2),
        "generated": ("tab:red", 1.6),
        "generated_codecs_only": ("tab:orange", 1.0),
        "synthetic_gt": ("tab:blue", 1.2),
        "baseline": ("tab:gray", 1.0),
        "real_through_codecs": ("tab:green", 1.0),
    }
    for ax, group in zip(axes.flat, JOINT_GROUPS):
        for name, per_group in samples.items():
            colour, width = styles[name]
            hist, edges = np.histogram(np.maximum(per_group[group], bins[0]), bins, density=False)
            ax.plot(np.sqrt(edges[1:] * edges[:-1]), hist / hist.sum(), color=colour, lw=width, label=name)
        ax.axvline(STILL_RAD_S, color="k", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_title(group.replace("_", " + "))
        ax.set_xlabel("angular speed (rad/s)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Angular speed per joint group: the real clip against motion for its speech (dotted: still)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def side_by_side_mp4(
    real_npz: Path, generated_npz: Path, wav: Path, path: Path, size: int = 384, camera: str = "upper"
) -> dict:
    """Real clip (left) and the agent (right) with the speech, rendered by render.play's pieces."""
    from render.mp4 import Mp4Writer
    from render.play import EncoderThread, frame_audio, load_motion_25fps
    from render.view import AvatarView, load_body

    motions = [load_motion_25fps(real_npz), load_motion_25fps(generated_npz)]
    n = min(len(m[0]) for m in motions)
    audio = frame_audio(wav, n)
    body = load_body(None)
    views = [AvatarView(body, size, size, camera=camera) for _ in motions]
    encoder = EncoderThread(Mp4Writer(path, 2 * size, size))
    committed = False
    try:
        for i in range(n):
            frames = [view.frame(m[0][i], m[1][i], m[2][i]) for view, m in zip(views, motions)]
            encoder.put(np.concatenate(frames, axis=1), audio[i])  # (size, 2 size, 3)
        committed = True
    finally:
        encoder.close(commit=committed)
        for view in views:
            view.close()
    return {"frames": n, "path": str(path)}


def _json_safe(value):
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (float, np.floating)):
        return None if not math.isfinite(float(value)) else round(float(value), 5)
    return value


def format_table(report: dict) -> str:
    names = [k for k in report if k not in ("real", "real_halves", "meta")]
    lines = [f"{'ratio to real':30s}" + "".join(f"{n:>32s}" for n in names)]
    for group in JOINT_GROUPS:
        for key in report["real"]["groups"][group]:
            row = [report[n]["ratios"]["groups"][group][key] for n in names]
            lines.append(f"{group + ' ' + key:30s}" + "".join(f"{v:32.2f}" for v in row))
    for section in ("hands", "feet", "face"):
        for key in report[names[0]]["ratios"][section]:
            row = [report[n]["ratios"][section][key] for n in names]
            lines.append(f"{key:30s}" + "".join(f"{'none':>32s}" if v is None else f"{v:32.2f}" for v in row))
    for group in JOINT_GROUPS:
        row = [report[n]["ratios"]["spectra"][group]["fast_power_share"] for n in names]
        lines.append(f"{group + ' fast_power_share':30s}" + "".join(f"{v:32.2f}" for v in row))
    for part in WORLD_PARTS:
        for key in report["real"]["world"][part]:
            row = [report[n]["ratios"]["world"][part][key] for n in names]
            lines.append(f"{part + ' in space ' + key:30s}" + "".join(f"{v:32.2f}" for v in row))
    lines.append(f"{'hand_height_overlap':30s}" + "".join(f"{report[n]['hand_height_overlap']:32.2f}" for n in names))
    lines.append(f"{'l1div':30s}" + "".join(f"{report[n]['ratios']['l1div']:32.2f}" for n in names))
    lines.append(f"{'beat_align - real':30s}" + "".join(f"{report[n]['beat_align_minus_real']:32.3f}" for n in names))
    lines.append(
        f"{'fgd_kinetic (absolute)':30s}" + "".join(f"{report[n]['protocol']['fgd_kinetic']:32.3f}" for n in names)
    )
    own = report["real_halves"]
    lines.append(f"\nthe speaker against himself (the clip's second {own['seconds_each']:.0f} s / its first):")
    for group in GOAL_GROUPS:
        values = own["ratios"]["groups"][group]
        lines.append(f"{group:30s}" + "  ".join(f"{key} {value:.2f}" for key, value in values.items()))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    limit_threads()
    p = argparse.ArgumentParser(prog="ecas realism", description=__doc__.splitlines()[0])
    p.add_argument(
        "--seed", type=int, default=0, help="sampling seed of the agent, the synthetic reference and the baseline"
    )
    p.add_argument("--out", help="directory for realism.json, speeds.png, side_by_side.mp4 and the agent's run")
    p.add_argument("--motion", help="reuse this motion.npz of the agent instead of running launch.py --speak")
    p.add_argument(
        "--config", type=Path, default=DEFAULT_APP_CONFIG, help="the agent's app config (launch.py --config)"
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="passed to launch.py (e.g. gesture.lm_checkpoint=runs/x/gesture_lm)",
    )
    p.add_argument("--synthetic", help="reuse this motion npz as the synthetic reference instead of generating it")
    p.add_argument(
        "--codecs",
        help="the agent's codecs, for the real clip's reconstruction (the ceiling; default: "
        "the config's gesture.codec_checkpoints)",
    )
    p.add_argument("--clip", default=str(REAL_CLIP), help="the real clip, without extension (.npz and .wav)")
    p.add_argument("--wav", help="the clip's speech when it is not CLIP.wav (e.g. BEAT2's wave16k/<take>.wav)")
    p.add_argument("--no-video", action="store_true", help="skip the side-by-side MP4")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    args = p.parse_args(argv)
    out = Path(args.out) if args.out else Path("runs") / f"realism_seed{args.seed}"
    real_npz, wav = Path(args.clip + ".npz"), Path(args.wav or args.clip + ".wav")
    try:
        given = tuple(Path(x) for x in (args.motion, args.synthetic) if x)
        for path in (real_npz, wav, MEAN_SPEED_NPY) + given:
            if not path.is_file():
                raise DataError(path, "not found")
        out.mkdir(parents=True, exist_ok=True)
        config = args.config.resolve()  # launch.py runs in the repository
        codecs = Path(args.codecs) if args.codecs else config_codecs(config, args.set)
        generated_npz = (
            Path(args.motion) if args.motion else speak_clip(wav, args.seed, out / "agent", config, args.set)
        )
        skeleton = Skeleton.default()
        real, generated = load_clip(real_npz), load_clip(generated_npz)
        n = min(len(real.poses), len(generated.poses))
        real = cut(real, n)
        synthetic = (
            cut(load_clip(args.synthetic), n)
            if args.synthetic
            else synthetic_reference(wav, n, args.seed, clip_words(wav, out / "words.json"))
        )
        motions = {"generated": cut(generated, n)}
        if not args.motion:  # the same agent without its runtime layers: what the LM and codecs alone carry
            plain_npz = speak_clip(
                wav,
                args.seed,
                out / "agent_codecs_only",
                config,
                args.set + [WITHOUT_LAYERS],
            )
            motions["generated_codecs_only"] = cut(load_clip(plain_npz), n)
        motions |= {
            "synthetic_gt": synthetic,
            "baseline": baseline_reference(real, args.seed),
            "real_through_codecs": cut(through_codecs(real, codecs), n),
        }
        report = build_report(real, motions, M.load_speech(wav), M.load_mean_speed(MEAN_SPEED_NPY), skeleton)
    except (DataError, ValueError, FileNotFoundError, subprocess.CalledProcessError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    report["meta"] = {
        "clip": real_npz.stem,
        "seconds": n / MOTION_FPS,
        "seed": args.seed,
        "generated_motion": str(generated_npz),
        "edge_s": EDGE_S,
        "still_rad_s": STILL_RAD_S,
    }
    plot_speeds(real, motions, out / "speeds.png")
    if not args.no_video:
        report["meta"]["video"] = side_by_side_mp4(real_npz, generated_npz, wav, out / "side_by_side.mp4")["path"]
    report = _json_safe(report)
    (out / "realism.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report) if args.json else format_table(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
