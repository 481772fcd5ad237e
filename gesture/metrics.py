"""Gesture metrics, following the reference evaluation protocol (MIBURI-FACTS section 6).

Protocol (``prepare_pair``):
1. both motions are brought to 25 fps (a 30 fps BEAT2 npz is slerp-resampled first);
2. the GT jaw replaces the predicted jaw;
3. both are resampled 25 -> 30 fps (slerp rotations, linear expressions);
4. joints come from forward kinematics with zero translation (the built-in skeleton, or a real
   SMPL-X model's joints when one is given);
5. ``TRIM_FRAMES`` (60) frames at 30 fps are dropped at each end for every metric. BeatAlign computes
   velocities on the whole clip and looks for beats inside the trimmed window only.

Units: joint positions in metres; MPJPE and L1div in metres; BeatAlign in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from scipy.signal import argrelextrema

from gesture.data.beat2 import read_motion
from gesture.data.errors import DataError
from gesture.regions import JAW_JOINT, MOTION_FPS
from gesture.rotation import resample_motion
from gesture.skeleton import NUM_JOINTS, Skeleton, forward_kinematics

METRIC_FPS = 30
TRIM_FRAMES = 60  # at 30 fps, each end
AUDIO_SAMPLE_RATE_HZ = 16_000
ONSET_HOP_SAMPLES = 512
BEAT_JOINTS = (3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21)
BEAT_MINIMA_ORDER = 7
BEAT_SPEED_THRESHOLD = 0.3  # in units of the joint's mean BEAT2 speed
BEAT_SIGMA_S = 0.3


@dataclass(frozen=True)
class MotionClip:
    """SMPL-X motion: poses (T, 55, 3) axis-angle, trans (T, 3), expressions (T, 100), at ``fps``."""

    poses: np.ndarray
    trans: np.ndarray
    expressions: np.ndarray
    fps: float

    def at_fps(self, fps: float) -> "MotionClip":
        if self.fps == fps:
            return self
        poses, trans, expressions = resample_motion(self.poses, self.trans, self.expressions, self.fps, fps)
        return MotionClip(poses, trans, expressions, fps)


def load_motion_clip(path: Path | str, default_fps: float = MOTION_FPS) -> MotionClip:
    """A BEAT2-style npz (poses (T, 165) or (T, 55, 3), trans, expressions, mocap_frame_rate or fps)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "motion file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
            poses = np.asarray(data["poses"]) if "poses" in keys else None
            if poses is not None and poses.ndim == 3:  # our own output layout
                missing = sorted({"trans", "expressions"} - keys)
                if missing:
                    raise DataError(path, f"motion file has no '{missing[0]}' array")
                fps = float(data["fps"]) if "fps" in keys else float(data.get("mocap_frame_rate", default_fps))
                return MotionClip(poses.astype(np.float32), data["trans"].astype(np.float32),
                                  data["expressions"].astype(np.float32), fps)
    except (OSError, ValueError) as err:
        raise DataError(path, f"not a readable npz ({err})") from err
    motion = read_motion(path)
    return MotionClip(motion.poses, motion.trans, motion.expressions, motion.fps)


@dataclass(frozen=True)
class PreparedPair:
    """Both motions after the protocol's steps 1-4, at 30 fps, untrimmed."""

    pred_joints: np.ndarray  # (T, 55, 3) metres, zero translation
    gt_joints: np.ndarray
    pred_expressions: np.ndarray  # (T, 100)
    gt_expressions: np.ndarray
    pred_poses: np.ndarray  # (T, 55, 3) axis-angle (jaw = GT jaw)
    gt_poses: np.ndarray


def joints_zero_translation(poses: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    with torch.no_grad():
        joints, _ = forward_kinematics(skeleton, torch.as_tensor(np.asarray(poses, np.float32)))
    return joints.numpy()


def prepare_pair(pred: MotionClip, gt: MotionClip, skeleton: Optional[Skeleton] = None) -> PreparedPair:
    skeleton = skeleton or Skeleton.default()
    pred, gt = pred.at_fps(MOTION_FPS), gt.at_fps(MOTION_FPS)
    n = min(len(pred.poses), len(gt.poses))
    if n < 2:
        raise ValueError(f"metrics: need at least 2 frames at {MOTION_FPS} fps, got {n}")
    pred_poses = np.array(pred.poses[:n], copy=True)
    pred_poses[:, JAW_JOINT] = gt.poses[:n, JAW_JOINT]
    pred30 = MotionClip(pred_poses, pred.trans[:n], pred.expressions[:n], MOTION_FPS).at_fps(METRIC_FPS)
    gt30 = MotionClip(gt.poses[:n], gt.trans[:n], gt.expressions[:n], MOTION_FPS).at_fps(METRIC_FPS)
    return PreparedPair(
        pred_joints=joints_zero_translation(pred30.poses, skeleton),
        gt_joints=joints_zero_translation(gt30.poses, skeleton),
        pred_expressions=pred30.expressions,
        gt_expressions=gt30.expressions,
        pred_poses=pred30.poses,
        gt_poses=gt30.poses,
    )


def trim(x: np.ndarray, frames: int = TRIM_FRAMES) -> np.ndarray:
    if len(x) <= 2 * frames:
        raise ValueError(f"metrics: clip of {len(x)} frames at {METRIC_FPS} fps is too short to drop {frames} at each end")
    return x[frames : len(x) - frames]


# ---------------------------------------------------------------- pose metrics


def mpjpe_m(pred_joints: np.ndarray, gt_joints: np.ndarray) -> float:
    """Mean per-joint position error (metres) over frames and joints."""
    return float(np.linalg.norm(pred_joints - gt_joints, axis=-1).mean())


def l1_divergence(joints: np.ndarray) -> float:
    """Diversity: sum over joints and axes of |x - clip mean|, averaged over frames (metres)."""
    flat = joints.reshape(len(joints), -1)  # (T, 55 * 3)
    return float(np.abs(flat - flat.mean(0)).sum() / len(flat))


def expression_mse(pred_expressions: np.ndarray, gt_expressions: np.ndarray) -> float:
    """Facial MSE without an SMPL-X model: mean squared error of the 100 FLAME expression coefficients.

    (The GT jaw is substituted by the protocol, so the jaw contributes nothing.)
    """
    return float(np.mean((pred_expressions - gt_expressions) ** 2))


def face_vertex_mse(pred_expressions: np.ndarray, gt_expressions: np.ndarray, expression_dirs: np.ndarray) -> float:
    """Facial MSE on vertices: expression_dirs (V, 3, E) from an SMPL-X model (shapedirs[..., 300:400]).

    Only vertices that expressions move (the face) are averaged, in squared metres.
    """
    face = np.abs(expression_dirs).sum(axis=(1, 2)) > 0  # (V,)
    dirs = expression_dirs[face]  # (Vf, 3, E)
    diff = np.einsum("vce,te->tvc", dirs, pred_expressions - gt_expressions)  # (T, Vf, 3)
    return float(np.mean(np.sum(diff**2, axis=-1)))


def load_expression_dirs(smplx_model: Path | str) -> np.ndarray:
    """(V, 3, 100) expression blend shapes of an SMPL-X npz (shapedirs columns 300..399)."""
    path = Path(smplx_model)
    try:
        with np.load(path, allow_pickle=True) as data:
            shapedirs = np.asarray(data["shapedirs"], np.float64)
    except FileNotFoundError:
        raise DataError(path, "SMPL-X model file not found") from None
    except KeyError:
        raise DataError(path, "SMPL-X model has no 'shapedirs'") from None
    if shapedirs.ndim != 3 or shapedirs.shape[-1] < 400:
        raise DataError(path, f"'shapedirs' must be (V, 3, >=400) to hold expressions, got {shapedirs.shape}")
    return shapedirs[..., 300:400]


# ---------------------------------------------------------------- BeatAlign


def audio_onsets_s(audio: np.ndarray, sample_rate_hz: int = AUDIO_SAMPLE_RATE_HZ) -> np.ndarray:
    """Onset times (s) by librosa's onset detector, hop 512 at 16 kHz."""
    import librosa

    if sample_rate_hz != AUDIO_SAMPLE_RATE_HZ:
        audio = librosa.resample(audio, orig_sr=sample_rate_hz, target_sr=AUDIO_SAMPLE_RATE_HZ)
    return librosa.onset.onset_detect(
        y=np.asarray(audio, np.float32), sr=AUDIO_SAMPLE_RATE_HZ, hop_length=ONSET_HOP_SAMPLES, units="time"
    )


def joint_speeds(joints: np.ndarray, fps: float) -> np.ndarray:
    """(T, J, 3) -> (T, J) m/s: central differences inside, one-sided at the ends."""
    vel = np.empty_like(joints)
    vel[1:-1] = (joints[2:] - joints[:-2]) * (fps / 2)
    vel[0] = (joints[1] - joints[0]) * fps
    vel[-1] = (joints[-1] - joints[-2]) * fps
    return np.linalg.norm(vel, axis=-1)


def motion_beats_s(
    joints: np.ndarray,
    mean_speed: np.ndarray,
    fps: float = METRIC_FPS,
    trim_frames: int = TRIM_FRAMES,
    reference_quirk: bool = True,
) -> list[np.ndarray]:
    """Per beat joint, the times (s, relative to the trimmed window's start) of its velocity minima.

    A minimum (argrelextrema, order 7, inside the trimmed window) counts when the joint's normalised
    speed exceeds 0.3 there. ``reference_quirk=True`` reproduces the reference, which tests the
    threshold at the minimum's window-relative index as if it were an absolute frame; False tests it
    at the right frame.
    """
    speed = joint_speeds(joints, fps) / mean_speed[None, : joints.shape[1]]  # (T, J)
    start, end = trim_frames, len(joints) - trim_frames
    beats = []
    for j in BEAT_JOINTS:
        fast = speed[:, j] > BEAT_SPEED_THRESHOLD  # (T,) absolute frames
        minima = argrelextrema(speed[start:end, j], np.less, order=BEAT_MINIMA_ORDER)[0]  # window-relative
        frame_tested = minima if reference_quirk else minima + start
        beats.append(minima[fast[frame_tested]] / fps)
    return beats


def beat_align_score(onsets_s: np.ndarray, beats_s: list[np.ndarray], sigma_s: float = BEAT_SIGMA_S) -> float:
    """Mean over joints of mean over onsets of exp(-d² / 2σ²), d = distance to the joint's nearest beat."""
    if len(onsets_s) == 0:
        return float("nan")
    scores = []
    for beats in beats_s:
        if len(beats) == 0:
            scores.append(0.0)
            continue
        d = np.abs(onsets_s[:, None] - beats[None, :]).min(axis=1)  # (n_onsets,)
        scores.append(float(np.exp(-(d**2) / (2 * sigma_s**2)).mean()))
    return float(np.mean(scores))


def beat_align(
    joints: np.ndarray,
    onsets_s: np.ndarray,
    mean_speed: np.ndarray,
    fps: float = METRIC_FPS,
    trim_frames: int = TRIM_FRAMES,
    reference_quirk: bool = True,
) -> float:
    """BeatAlign of 30 fps joints (untrimmed, zero translation) against the audio onsets of the whole clip."""
    window_start_s, window_end_s = trim_frames / fps, (len(joints) - trim_frames) / fps
    onsets = onsets_s[(onsets_s >= window_start_s) & (onsets_s <= window_end_s)] - window_start_s
    beats = motion_beats_s(joints, mean_speed, fps, trim_frames, reference_quirk)
    return beat_align_score(onsets, beats)


def load_mean_speed(path: Path | str) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "BeatAlign normaliser (mean_vel_smplxflame_30.npy) not found")
    mean = np.load(path).astype(np.float64).reshape(-1)
    if len(mean) < NUM_JOINTS or (mean <= 0).any():
        raise DataError(path, f"expected {NUM_JOINTS} positive mean joint speeds, got shape {mean.shape}")
    return mean
