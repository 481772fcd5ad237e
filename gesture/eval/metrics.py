"""Gesture metrics computed exactly as the reference computes them (docs/reference_facts.md §6).

The reference protocol, step by step (checked number for number against the reference's own outputs in
``../shared/reference/metrics_golden`` by tests/test_metrics_golden.py):
0. input at 25 fps (a 30 fps BEAT2 npz is first brought to 25 fps: per-joint slerp, linear translation);
1. 25 -> 30 fps: per-joint slerp at source frames 0, 5/6, 10/6, ... (float64 axis-angle);
2. the GT jaw replaces the predicted jaw;
3. rotation round trip: axis-angle -> matrix -> 6D, cast to float32, 6D -> matrix -> axis-angle;
4. joints: an SMPL-X-format body in float32, chunks of 64 frames, the GT clip's betas (as many as the body has),
   zero expressions and zero translation; the first 55 joints. Without a body file, the built-in skeleton
   (gesture.body.skeleton, no shape) stands in for it;
5. L1div and MPJPE over EVERY frame at 30 fps;
6. BeatAlign: audio onsets of librosa's detector on the speech brought to 22050 Hz and back to 16 kHz, cut to the
   motion and with 2 s removed at each end; motion beats = velocity minima (order 7) inside the window that drops
   60 frames at each end, kept where the normalised speed exceeds 0.3. Two reference quirks are kept
   (``reference_quirk``):
   - the speeds are those of the joint array as the reference's L1div leaves it. L1div overwrites the array in
     place with |x - clip mean| per coordinate, and the beats are looked for afterwards on that same array. So a
     joint moving fast through its clip-mean position looks still for a frame there, and that frame can become
     a beat;
   - the threshold is tested at the minimum's window-relative index used as an absolute frame.

What we compute differently is reported under other names, with the reason:
- ``beat_align_corrected``: the speed minima of the joints themselves, with the threshold tested at the minimum's
  own frame. Both of the reference's slips are undone.

The onset detector is librosa's algorithm (onset strength on a 128-band mel spectrogram, peak picking) written
here in numpy and tested equal to librosa: librosa's peak picker runs in numba, whose on-disk cache, shared by
every process, crashed evaluations with SIGSEGV once two processes had written it at once (issue 15). Nothing
here imports numba.

Units: joint positions in metres; MPJPE and L1div in metres; BeatAlign in [0, 1].
"""

from __future__ import annotations

import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import numpy as np
import torch
from scipy.signal import argrelextrema, get_window

from ecas.core.body import JAW_JOINT, NUM_EXPRESSIONS, NUM_JOINTS, UPPER_BODY_JOINTS
from ecas.core.errors import DataError
from ecas.core.mel import mel_filterbank
from ecas.core.timing import MOTION_FPS
from gesture.body.rotation import axis_angle_to_rot6d, resample_motion, rot6d_to_axis_angle
from gesture.body.skeleton import JOINT_NAMES, PARENTS, Skeleton, forward_kinematics, read_smplx_file
from gesture.data.audio import read_audio

METRIC_FPS = 30
TRIM_FRAMES = 60  # at 30 fps, each end: only where motion beats are looked for
BODY_CHUNK_FRAMES = 64
AUDIO_SAMPLE_RATE_HZ = 16_000
LOAD_SAMPLE_RATE_HZ = 22_050  # librosa.load's default rate, which the reference's audio passes through
ONSET_HOP_SAMPLES = 512
ONSET_FFT_SAMPLES = 2048
ONSET_MEL_BANDS = 128
BEAT_JOINTS = UPPER_BODY_JOINTS  # the body without the hands and legs
BEAT_MINIMA_ORDER = 7
BEAT_SPEED_THRESHOLD = 0.3  # in units of the joint's mean BEAT2 speed
BEAT_SIGMA_S = 0.3
POSE_DIM = NUM_JOINTS * 3


# ---------------------------------------------------------------- motion files


@dataclass(frozen=True)
class MotionClip:
    """SMPL-X motion: poses (T, 55, 3) axis-angle, trans (T, 3), expressions (T, E) or None, at ``fps``;
    betas (B,) or None (the GT's betas shape the body)."""

    poses: np.ndarray
    trans: np.ndarray
    expressions: np.ndarray | None
    fps: float
    betas: np.ndarray | None = None

    def at_fps(self, fps: float) -> MotionClip:
        if self.fps == fps:
            return self
        poses, trans, expressions = resample_motion(self.poses, self.trans, self.expressions, self.fps, fps)
        return MotionClip(poses, trans, expressions, fps, self.betas)


def _numeric(data, key: str, path: Path) -> np.ndarray:
    try:
        arr = data[key]
    except ValueError as err:  # object arrays need allow_pickle, which we never give
        raise DataError(path, f"'{key}' holds Python objects, not numbers ({err})") from None
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise DataError(path, f"'{key}' must hold numbers, got dtype {arr.dtype}")
    if not np.isfinite(arr).all():
        raise DataError(path, f"'{key}' contains NaN or inf")
    return arr


def load_motion_clip(path: Path | str, default_fps: float = MOTION_FPS) -> MotionClip:
    """A BEAT2-style npz: poses (T, 165) or (T, 55, 3); optional trans (T, 3), expressions (T, E), betas;
    the rate from ``mocap_frame_rate`` or ``fps`` (default 25). Every mistake is a DataError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "motion file not found")
    if not zipfile.is_zipfile(path):
        raise DataError(path, "not an npz file (an npz is a zip archive of .npy arrays)")
    try:
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
            if "poses" not in keys:
                listed = ", ".join(sorted(keys)) or "none"
                raise DataError(path, f"motion file has no 'poses' array (arrays: {listed})")
            poses = _numeric(data, "poses", path)
            t = len(poses)
            if poses.ndim == 2 and poses.shape[1] == POSE_DIM:
                poses = poses.reshape(t, NUM_JOINTS, 3)  # (T, 165) -> (T, 55, 3)
            if poses.ndim != 3 or poses.shape[1:] != (NUM_JOINTS, 3):
                raise DataError(path, f"'poses' must be (T, {POSE_DIM}) or (T, {NUM_JOINTS}, 3), got {poses.shape}")
            if t < 2:
                raise DataError(path, f"motion has {t} frame(s); need at least 2")
            trans = _numeric(data, "trans", path) if "trans" in keys else np.zeros((t, 3))
            if trans.shape != (t, 3):
                raise DataError(path, f"'trans' must be ({t}, 3) to match 'poses', got {trans.shape}")
            expressions = None
            if "expressions" in keys:
                expressions = _numeric(data, "expressions", path)
                if expressions.ndim != 2 or len(expressions) != t:
                    raise DataError(path, f"'expressions' must be ({t}, E) to match 'poses', got {expressions.shape}")
                expressions = expressions.astype(np.float32)
            betas = _numeric(data, "betas", path).reshape(-1).astype(np.float32) if "betas" in keys else None
            fps = _frame_rate(data, keys, path, default_fps)
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise DataError(path, f"not a readable npz ({err})") from err
    return MotionClip(poses.astype(np.float32), trans.astype(np.float32), expressions, fps, betas)


def _frame_rate(data, keys: set, path: Path, default_fps: float) -> float:
    for key in ("mocap_frame_rate", "fps"):
        if key in keys:
            value = _numeric(data, key, path).reshape(-1)
            if value.size != 1 or value[0] <= 0:
                raise DataError(path, f"'{key}' must be one positive number, got {value}")
            return float(value[0])
    return float(default_fps)


# ---------------------------------------------------------------- bodies


class SmplxBody:
    """Joints of an SMPL-X-format body file (npz or pkl: v_template, shapedirs, J_regressor, kintree_table).

    ``shapedirs`` (V, 3, K) holds the shape components and then the expression components. Like the ``smplx``
    package: a file with K >= 400 has 300 shape components (expressions from 300), a smaller one 10 (expressions
    from 10; the common 10 + 10 file). ``num_shape_components`` overrides that. Joints are computed with as many
    of the clip's betas as the body has, zero expressions (they move no joint), zero translation; the hand means
    are not added (BEAT2 poses are full hand poses).
    """

    def __init__(self, path: Path | str, num_shape_components: int | None = None):
        model = read_smplx_file(Path(path))
        self.path = Path(path)
        self.v_template = _body_array(model, "v_template", self.path).astype(np.float32)  # (V, 3)
        shapedirs = _body_array(model, "shapedirs", self.path).astype(np.float32)
        if shapedirs.ndim != 3 or shapedirs.shape[:2] != self.v_template.shape:
            raise DataError(
                self.path, f"'shapedirs' must be (V, 3, K) with V = {len(self.v_template)}, got {shapedirs.shape}"
            )
        k = shapedirs.shape[-1]
        default = 300 if k >= 400 else min(10, k)
        self.num_shape_components = default if num_shape_components is None else int(num_shape_components)
        if not 0 <= self.num_shape_components <= k:
            raise DataError(self.path, f"num_shape_components {self.num_shape_components} is outside 0..{k}")
        self.shapedirs = shapedirs[..., : self.num_shape_components]  # (V, 3, S)
        self.expression_dirs = shapedirs[..., self.num_shape_components : self.num_shape_components + NUM_EXPRESSIONS]
        regressor = model.get("J_regressor")
        if regressor is None:
            raise DataError(self.path, "SMPL-X model has no 'J_regressor'")
        if hasattr(regressor, "toarray"):  # scipy sparse in the .pkl release
            regressor = regressor.toarray()
        self.j_regressor = np.asarray(regressor, np.float32)[:NUM_JOINTS]  # (55, V)
        if self.j_regressor.shape != (NUM_JOINTS, len(self.v_template)):
            raise DataError(
                self.path, f"'J_regressor' must be ({NUM_JOINTS}, {len(self.v_template)}), got {np.shape(regressor)}"
            )
        parents = PARENTS
        if "kintree_table" in model:
            table = np.asarray(model["kintree_table"]).astype(np.int64)
            parents = tuple(int(p) if i else -1 for i, p in enumerate(table[0][:NUM_JOINTS]))
        self.parents = parents

    def rest_joints(self, betas: np.ndarray | None) -> np.ndarray:
        """(55, 3) float32: J_regressor @ (v_template + shapedirs · betas[:S])."""
        coeffs = np.zeros(self.num_shape_components, np.float32)
        if betas is not None:
            n = min(len(betas), self.num_shape_components)
            coeffs[:n] = np.asarray(betas, np.float32).reshape(-1)[:n]
        shaped = self.v_template + np.einsum("vcs,s->vc", self.shapedirs, coeffs)  # (V, 3)
        return (self.j_regressor @ shaped).astype(np.float32)

    def skeleton(self, betas: np.ndarray | None) -> Skeleton:
        return Skeleton(JOINT_NAMES, self.parents, self.rest_joints(betas))


def _body_array(model: dict, key: str, path: Path) -> np.ndarray:
    if key not in model:
        raise DataError(path, f"SMPL-X model has no '{key}'")
    return np.asarray(model[key])


Body = Union[Skeleton, SmplxBody]


def joints_zero_translation(poses: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """(T, 55, 3) axis-angle -> (T, 55, 3) float32 joints (metres), zero translation, in float32 chunks of 64."""
    poses = np.asarray(poses, np.float32)
    out = np.empty(poses.shape, np.float32)
    with torch.no_grad():
        for start in range(0, len(poses), BODY_CHUNK_FRAMES):
            chunk = torch.from_numpy(np.ascontiguousarray(poses[start : start + BODY_CHUNK_FRAMES]))
            out[start : start + BODY_CHUNK_FRAMES] = forward_kinematics(skeleton, chunk)[0].numpy()
    return out


def body_skeleton(body: Body | None, betas: np.ndarray | None) -> Skeleton:
    """The skeleton the joints come from: a body file shaped by ``betas``, a given skeleton, or the built-in one."""
    if body is None:
        return Skeleton.default()
    if isinstance(body, SmplxBody):
        return body.skeleton(betas)
    return body


# ---------------------------------------------------------------- protocol steps 1-4


def rotation_round_trip(poses_aa: np.ndarray) -> np.ndarray:
    """Step 3: axis-angle -> matrix -> 6D, cast to float32, -> matrix -> axis-angle (float32)."""
    rot6d = axis_angle_to_rot6d(np.asarray(poses_aa, np.float64)).astype(np.float32)  # (..., 6)
    return rot6d_to_axis_angle(rot6d)


@dataclass(frozen=True)
class PreparedPair:
    """Both motions after the protocol's steps 1-4, at 30 fps, every frame."""

    pred_joints: np.ndarray  # (T, 55, 3) metres, zero translation
    gt_joints: np.ndarray
    pred_expressions: np.ndarray | None  # (T, E), None when either file has none
    gt_expressions: np.ndarray | None
    pred_poses: np.ndarray  # (T, 55, 3) axis-angle after the round trip (jaw = GT jaw)
    gt_poses: np.ndarray


def prepare_pair(pred: MotionClip, gt: MotionClip, body: Body | None = None) -> PreparedPair:
    """Steps 0-4 for a prediction and its GT; the joints use the GT's betas for both."""
    pred, gt = pred.at_fps(MOTION_FPS), gt.at_fps(MOTION_FPS)
    n = min(len(pred.poses), len(gt.poses))
    if n < 2:
        raise ValueError(f"metrics: need at least 2 frames at {MOTION_FPS} fps, got {n}")
    pred_poses = np.array(pred.poses[:n], np.float64)
    pred_poses[:, JAW_JOINT] = gt.poses[:n, JAW_JOINT]
    with_face = pred.expressions is not None and gt.expressions is not None
    width = min(pred.expressions.shape[1], gt.expressions.shape[1]) if with_face else 0
    pred30 = MotionClip(
        pred_poses, pred.trans[:n], pred.expressions[:n, :width] if with_face else None, MOTION_FPS
    ).at_fps(METRIC_FPS)
    gt30 = MotionClip(
        np.asarray(gt.poses[:n], np.float64),
        gt.trans[:n],
        gt.expressions[:n, :width] if with_face else None,
        MOTION_FPS,
    ).at_fps(METRIC_FPS)
    pred_rt, gt_rt = rotation_round_trip(pred30.poses), rotation_round_trip(gt30.poses)
    skeleton = body_skeleton(body, gt.betas)
    return PreparedPair(
        pred_joints=joints_zero_translation(pred_rt, skeleton),
        gt_joints=joints_zero_translation(gt_rt, skeleton),
        pred_expressions=pred30.expressions,
        gt_expressions=gt30.expressions,
        pred_poses=pred_rt,
        gt_poses=gt_rt,
    )


# ---------------------------------------------------------------- pose metrics


def mpjpe_m(pred_joints: np.ndarray, gt_joints: np.ndarray) -> float:
    """Mean per-joint position error (metres) over frames and joints."""
    return float(np.linalg.norm(pred_joints - gt_joints, axis=-1).mean())


def l1_div(joints: np.ndarray) -> float:
    """L1 diversity (metres): Σ over frames and the 165 coordinates of |x − clip mean|, divided by the frames.

    The reference protocol passes every 30 fps frame of the clip (no trimming)."""
    flat = np.asarray(joints).reshape(len(joints), -1)  # (T, 55 * 3)
    return float(np.abs(flat - flat.mean(0)).sum() / len(flat))


def expression_mse(pred_expressions: np.ndarray, gt_expressions: np.ndarray) -> float:
    """Facial MSE without an SMPL-X model: mean squared error of the FLAME expression coefficients.

    (The GT jaw is substituted by the protocol, so the jaw contributes nothing.)
    """
    return float(np.mean((pred_expressions - gt_expressions) ** 2))


def face_vertex_mse(pred_expressions: np.ndarray, gt_expressions: np.ndarray, expression_dirs: np.ndarray) -> float:
    """Facial MSE on vertices: expression_dirs (V, 3, E) of an SMPL-X body (``SmplxBody.expression_dirs``).

    Only vertices that expressions move (the face) are averaged, in squared metres; the first E coefficients
    are used.
    """
    face = np.abs(expression_dirs).sum(axis=(1, 2)) > 0  # (V,)
    dirs = expression_dirs[face]  # (Vf, 3, E)
    e = dirs.shape[-1]
    diff = np.einsum("vce,te->tvc", dirs, pred_expressions[:, :e] - gt_expressions[:, :e])  # (T, Vf, 3)
    return float(np.mean(np.sum(diff**2, axis=-1)))


# ---------------------------------------------------------------- BeatAlign: audio


@dataclass(frozen=True)
class SpeechAudio:
    """Mono float32 samples at their file's own rate."""

    pcm: np.ndarray
    sample_rate_hz: int


def load_speech(path: Path | str) -> SpeechAudio:
    """A speech file as librosa.load reads it (float32, channels averaged), before any resampling."""
    path = Path(path)
    pcm, rate = read_audio(path)  # (N, C)
    if not np.isfinite(pcm).all():
        raise DataError(path, "audio contains NaN or inf samples")
    return SpeechAudio(pcm.mean(axis=1) if pcm.shape[1] > 1 else pcm[:, 0], rate)


def resample_like_librosa(y: np.ndarray, orig_hz: int, target_hz: int) -> np.ndarray:
    """``librosa.resample(y, orig_sr, target_sr)`` with its default soxr 'HQ' filter, length ceil(N·ratio)."""
    import soxr

    if orig_hz == target_hz:
        return y
    n_out = int(np.ceil(len(y) * (float(target_hz) / orig_hz)))
    out = soxr.resample(y, orig_hz, target_hz, quality="soxr_hq")
    out = out[:n_out] if len(out) >= n_out else np.pad(out, (0, n_out - len(out)))
    return np.asarray(out, dtype=y.dtype)


def speech_at_16k(speech: SpeechAudio) -> np.ndarray:
    """The reference's audio: loaded at librosa's default 22050 Hz, then resampled to 16 kHz."""
    y = resample_like_librosa(np.asarray(speech.pcm, np.float32), speech.sample_rate_hz, LOAD_SAMPLE_RATE_HZ)
    return resample_like_librosa(y, LOAD_SAMPLE_RATE_HZ, AUDIO_SAMPLE_RATE_HZ)


def beat_align_audio_window(audio_16k: np.ndarray, n_frames_30fps: int) -> np.ndarray:
    """The samples whose onsets BeatAlign uses: the audio cut to the motion (``int(16000 / 30 · n)`` samples),
    then 2 s (60 frames) removed at each end -- the end counted, as the reference does, from the uncut length."""
    margin = int(TRIM_FRAMES / METRIC_FPS * AUDIO_SAMPLE_RATE_HZ)
    cut = audio_16k[: int(AUDIO_SAMPLE_RATE_HZ / METRIC_FPS * n_frames_30fps)]
    return cut[margin : len(audio_16k) - margin]


def onset_strength(
    y: np.ndarray, sample_rate_hz: int, hop: int = ONSET_HOP_SAMPLES, n_fft: int = ONSET_FFT_SAMPLES
) -> np.ndarray:
    """(frames,) float32 spectral flux of a centred 128-band log-mel spectrogram (librosa.onset.onset_strength
    with its defaults), computed with the same array operations in the same memory order, so equal to it."""
    y = np.asarray(y, np.float32)
    padded = np.pad(y, n_fft // 2)  # centred frames, zero padding
    frames = np.lib.stride_tricks.sliding_window_view(padded, n_fft)[::hop]  # (T, n_fft)
    window = get_window("hann", n_fft, fftbins=True)  # float64, periodic
    spectrum = np.fft.rfft(frames * window, axis=-1).astype(np.complex64)  # (T, F)
    power = (np.abs(spectrum) ** 2).T  # (F, T), column-major like librosa's stft matrix
    mel = np.abs(
        np.einsum("...ft,mf->...mt", power, mel_filterbank(sample_rate_hz, n_fft, ONSET_MEL_BANDS), optimize=True)
    )
    log_mel = 10.0 * np.log10(np.maximum(1e-10, mel))  # dB re 1.0, floored 80 dB below the peak
    log_mel -= 10.0 * np.log10(np.maximum(1e-10, 1.0))
    log_mel = np.maximum(log_mel, log_mel.max() - 80.0)
    flux = np.maximum(0.0, log_mel[..., 1:] - log_mel[..., :-1])  # (M, T - 1)
    mean_flux = np.empty((1, flux.shape[-1]), order="F" if np.isfortran(flux) else "C", dtype=flux.dtype)
    mean_flux[0] = np.mean(flux, axis=-2)
    lag_and_centre = 1 + n_fft // (2 * hop)
    return np.pad(mean_flux, [(0, 0), (lag_and_centre, 0)], mode="constant")[0, : log_mel.shape[-1]]


def peak_pick(
    x: np.ndarray, pre_max: int, post_max: int, pre_avg: int, post_avg: int, delta: float, wait: int
) -> np.ndarray:
    """Indices n with x[n] == max(x[n - pre_max : n + post_max]) and x[n] >= mean(x[n - pre_avg : n + post_avg])
    + delta, taken greedily at least ``wait`` + 1 apart (librosa.util.peak_pick, numpy instead of numba).

    Windows are clipped to the signal. The mean is accumulated in x's dtype left to right and then divided in
    float64, and delta is a float32, as in librosa's compiled kernel, so ties fall the same way.
    """
    x = np.asarray(x)
    n = len(x)
    idx = np.arange(n)
    is_max = np.ones(n, bool)
    for k in range(-pre_max, post_max):
        j = idx + k
        inside = (j >= 0) & (j < n)
        is_max[inside] &= x[idx[inside]] >= x[j[inside]]
    total = np.zeros(n, x.dtype)
    for k in range(-pre_avg, post_avg):  # left to right, as the kernel sums
        j = np.clip(idx + k, 0, n - 1)
        total = total + np.where((idx + k >= 0) & (idx + k < n), x[j], x.dtype.type(0))
    count = np.minimum(idx + post_avg, n) - np.maximum(0, idx - pre_avg)
    above = x.astype(np.float64) >= total.astype(np.float64) / count + np.float64(np.float32(delta))
    peaks, last = [], -np.inf
    for i in np.flatnonzero(is_max & above):
        if i > last + wait:
            peaks.append(i)
            last = i
    return np.array(peaks, dtype=np.int64)


def onset_times_s(
    y: np.ndarray, sample_rate_hz: int = AUDIO_SAMPLE_RATE_HZ, hop: int = ONSET_HOP_SAMPLES
) -> np.ndarray:
    """Onset times (s) as ``librosa.onset.onset_detect(y, sr, hop_length=hop, units='time')``."""
    envelope = onset_strength(y, sample_rate_hz, hop)
    envelope = envelope - np.min(envelope, keepdims=True, axis=-1)
    envelope /= np.max(envelope, keepdims=True, axis=-1) + np.finfo(envelope.dtype).tiny
    if not envelope.any() or not np.all(np.isfinite(envelope)):
        return np.zeros(0)
    frames_of = lambda seconds: int(np.ceil(seconds * sample_rate_hz // hop))
    frames = peak_pick(
        envelope,
        pre_max=frames_of(0.03),
        post_max=frames_of(0.0) + 1,
        pre_avg=frames_of(0.10),
        post_avg=frames_of(0.10) + 1,
        delta=0.07,
        wait=frames_of(0.03),
    )
    return (frames * hop).astype(int) / float(sample_rate_hz)


def beat_align_onsets_s(speech: SpeechAudio | np.ndarray, n_frames_30fps: int) -> np.ndarray:
    """The audio onsets BeatAlign compares with, in seconds from the start of the beat window (frame 60).

    ``speech``: a SpeechAudio at its own rate, or a plain array taken to be 16 kHz samples."""
    if not isinstance(speech, SpeechAudio):
        speech = SpeechAudio(np.asarray(speech, np.float32), AUDIO_SAMPLE_RATE_HZ)
    window = beat_align_audio_window(speech_at_16k(speech), n_frames_30fps)
    if len(window) == 0:
        return np.zeros(0)
    return onset_times_s(window)


# ---------------------------------------------------------------- BeatAlign: motion


def joint_speeds(joints: np.ndarray, fps: float) -> np.ndarray:
    """(T, J, 3) -> (T, J) m/s: central differences inside, one-sided at the ends."""
    vel = np.empty_like(joints)
    vel[1:-1] = (joints[2:] - joints[:-2]) * (fps / 2)
    vel[0] = (joints[1] - joints[0]) * fps
    vel[-1] = (joints[-1] - joints[-2]) * fps
    return np.linalg.norm(vel, axis=-1)


def joints_as_left_by_l1div(joints: np.ndarray) -> np.ndarray:
    """(T, J, 3) -> (T, J, 3) float32: |x - clip mean| for every coordinate.

    This is the joint array as the reference's L1div leaves it. L1div overwrites its input in place with these
    deviations, and the reference then detects BeatAlign's motion beats on that same array. Checked on the
    golden fixture: 5017 of the reference's 5024 beat frames are minima of this array's speed, and 46 of the 55
    joints agree exactly. The true joints' speed gives 4033. The rest are near-ties that the joints' ~1 µm
    difference from the reference's decides.
    """
    flat = np.asarray(joints, np.float32).reshape(len(joints), -1)  # (T, J * 3), float32 like the reference's
    return np.abs(flat - flat.mean(0)).reshape(np.shape(joints))


def speed_minima_beats(
    speed: np.ndarray, trim_frames: int = TRIM_FRAMES, slipped_threshold: bool = True
) -> list[np.ndarray]:
    """(T, J) normalised speeds -> for every joint the window-relative frames of its beats.

    A beat is a minimum of ``speed[trim_frames:T - trim_frames]`` (argrelextrema, order 7) where the speed
    exceeds 0.3. ``slipped_threshold`` tests the speed, as the reference does, at the minimum's
    window-relative index used as an absolute frame; False tests it at the minimum's own frame.
    """
    start, end = trim_frames, len(speed) - trim_frames
    beats = []
    for j in range(speed.shape[1]):
        fast = speed[:, j] > BEAT_SPEED_THRESHOLD  # (T,) absolute frames
        minima = argrelextrema(speed[start:end, j], np.less, order=BEAT_MINIMA_ORDER)[0]  # window-relative
        beats.append(minima[fast[minima if slipped_threshold else minima + start]])
    return beats


def motion_beat_frames(
    joints: np.ndarray,
    mean_speed: np.ndarray,
    fps: float = METRIC_FPS,
    trim_frames: int = TRIM_FRAMES,
    reference_quirk: bool = True,
) -> list[np.ndarray]:
    """For every joint, the frames (relative to the window start ``trim_frames``) of its motion beats.

    A beat is a velocity minimum (argrelextrema, order 7, inside the window that drops ``trim_frames`` at each
    end) where the speed, normalised by ``mean_speed``, exceeds 0.3. ``reference_quirk=True`` computes it as the
    reference does. The speeds are those of ``joints_as_left_by_l1div(joints)``, and the threshold is tested at
    the minimum's window-relative index used as an absolute frame. ``False`` uses the joints' own speeds and
    tests the threshold at the minimum's own frame.
    """
    if len(joints) <= 2 * trim_frames:
        raise ValueError(
            f"BeatAlign: clip of {len(joints)} frames at {fps:g} fps is too short to drop {trim_frames} at each end"
        )
    positions = joints_as_left_by_l1div(joints) if reference_quirk else joints
    speed = joint_speeds(positions, fps) / mean_speed[None, : joints.shape[1]]  # (T, J)
    return speed_minima_beats(speed, trim_frames, slipped_threshold=reference_quirk)


def beat_align_score(onsets_s: np.ndarray, beats_s: Sequence[np.ndarray], sigma_s: float = BEAT_SIGMA_S) -> float:
    """Mean over joints of mean over onsets of exp(-d² / 2σ²), d = distance to the joint's nearest beat;
    a joint without beats scores 0; NaN without onsets."""
    if len(onsets_s) == 0:
        return float("nan")
    scores = []
    for beats in beats_s:
        if len(beats) == 0:
            scores.append(0.0)
            continue
        d = np.abs(np.asarray(onsets_s)[:, None] - np.asarray(beats)[None, :]).min(axis=1)  # (n_onsets,)
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
    """BeatAlign of 30 fps joints (every frame, zero translation) against ``beat_align_onsets_s``'s onsets
    (seconds from the beat window's start); the mean over the joints 3, 6, 9, 12-21."""
    beats = motion_beat_frames(joints, mean_speed, fps, trim_frames, reference_quirk)
    return beat_align_score(onsets_s, [beats[j] / fps for j in BEAT_JOINTS])


def load_mean_speed(path: Path | str) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "BeatAlign normaliser (mean_vel_smplxflame_30.npy) not found")
    try:
        mean = np.load(path, allow_pickle=False).astype(np.float64).reshape(-1)
    except (OSError, ValueError) as err:
        raise DataError(path, f"not a readable .npy file ({err})") from err
    if len(mean) < NUM_JOINTS or not np.isfinite(mean).all() or (mean <= 0).any():
        raise DataError(path, f"expected {NUM_JOINTS} positive mean joint speeds, got shape {mean.shape}")
    return mean
