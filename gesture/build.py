"""Build the streaming gesture generator of a `gesture:` config section: checkpoints, spec check, sampling options,
idle gate and the runtime layers. The engine (`gesture.engine`) and the gesture stage (`gesture.process`) both build
theirs here, so they run the same generator.
"""

from __future__ import annotations

from ecas.core.body import COLLARS
from ecas.core.config import ConfigError
from ecas.core.timing import MOTION_FPS
from gesture.alternation_filter import AlternationFilter
from gesture.body.skeleton import Skeleton
from gesture.config import (
    AlternationFilterConfig,
    FaceLayerConfig,
    FootLockConfig,
    GestureConfig,
    MicroMotionConfig,
    StabilizerConfig,
)
from gesture.face_layer import FaceLayer
from gesture.foot_lock import FootLock
from gesture.generator import GestureGenerator
from gesture.lm.checkpoint import load_lm
from gesture.lm.codecs import load_codecs
from gesture.lm.idle import IdleGate, load_idle_slices
from gesture.micro_motion import HeadDrift, MicroMotion, calibrated_micro_motion
from gesture.nn.weights import UnsupportedFormError, require_fast_form
from gesture.stabilizer import ArmStabilizer


def build_generator(cfg: GestureConfig, seed: int) -> GestureGenerator:
    """The generator of a `gesture:` section: checkpoints, spec check, sampling options, idle gate."""
    if cfg.lm_checkpoint is None:
        raise ConfigError("gesture.lm_checkpoint: required (a directory written by python -m gesture.train_lm)")
    if cfg.codec_checkpoints is None:
        raise ConfigError("gesture.codec_checkpoints: required (a directory with upper/, lower/ and face/ codecs)")
    try:
        require_fast_form(cfg.dtype, "gesture.dtype", cfg.dtype_fallback, "gesture.dtype_fallback")
    except UnsupportedFormError as error:
        raise ConfigError(str(error)) from None
    expected = cfg.dialogue_spec
    lm = load_lm(cfg.lm_checkpoint, expected)
    codecs = load_codecs(cfg.codec_checkpoints)
    idle = None
    if cfg.idle.enabled:
        upper, face = load_idle_slices(cfg.idle.slices_dir)
        s = lm.sizes
        idle = IdleGate(
            upper,
            face,
            slice(0, s.n_upper),
            slice(s.face_levels.start, s.n_levels),
            cfg.idle.window_samples,
            cfg.idle.l2_threshold,
            cfg.idle.rewind_below_tokens,
        )
    return GestureGenerator(
        lm,
        codecs,
        temperature=cfg.temperature,
        top_p_temporal=cfg.top_p_temporal,
        top_p_depth=cfg.top_p_depth,
        cfg_scale=cfg.cfg_scale,
        speaker=cfg.speaker,
        seed=seed,
        dtype=cfg.dtype,
        hold_bias=cfg.hold_bias,
        hold_levels=cfg.hold_levels,
        idle_gate=idle,
        micro_motion=build_micro_motion(cfg.micro_motion, seed),
        face_layer=build_face_layer(cfg.face, seed),
        foot_lock=build_foot_lock(cfg.foot_lock),
        stabilizer=build_stabilizer(cfg.stabilizer),
        alternation_filter=build_alternation_filter(cfg.alternation_filter),
        initial_translation=cfg.initial_translation,
    )


def build_micro_motion(cfg: MicroMotionConfig, seed: int) -> MicroMotion | None:
    """The `gesture.micro_motion` layer, or None when it is off."""
    if not cfg.enabled:
        return None
    drift = HeadDrift(cfg.head_drift_rad, cfg.head_drift_hz, MOTION_FPS, seed) if cfg.head_drift_rad > 0 else None
    try:
        collars = {j: cfg.collar_cutoff_hz for j in COLLARS} if cfg.collar_cutoff_hz > 0 else {}
        return calibrated_micro_motion(cfg.joints, MOTION_FPS, seed, cfg.scale, drift, collars)
    except ValueError as error:
        raise ConfigError(f"gesture.micro_motion.joints: {error}") from None


def build_face_layer(cfg: FaceLayerConfig, seed: int) -> FaceLayer | None:
    """The `gesture.face` layer on the decoded expressions, or None when it is off."""
    if not cfg.enabled:
        return None
    return FaceLayer(MOTION_FPS, seed, cfg.blinks_per_minute, cfg.brow_cutoff_hz)


def build_foot_lock(cfg: FootLockConfig) -> FootLock | None:
    """The `gesture.foot_lock` layer on the decoded legs (the built-in skeleton, as the training data's), or None."""
    if not cfg.enabled:
        return None
    return FootLock(Skeleton.default(), MOTION_FPS, cfg.release_m, cfg.release_speaking_m, cfg.blend_s, cfg.step_s)


def build_stabilizer(cfg: StabilizerConfig) -> ArmStabilizer | None:
    """The `gesture.stabilizer` smoothing of the output arms, or None when it is off."""
    if not cfg.enabled:
        return None
    try:
        return ArmStabilizer(
            cfg.joints,
            MOTION_FPS,
            cfg.min_cutoff_hz,
            cfg.speed_gain_hz,
            cfg.speed_cutoff_hz,
            cfg.hold_rad,
            cfg.settle_share,
        )
    except ValueError as error:
        raise ConfigError(f"gesture.stabilizer: {error}") from None


def build_alternation_filter(cfg: AlternationFilterConfig) -> AlternationFilter | None:
    """The `gesture.alternation_filter` on the decoded motion, or None when it is off."""
    if not cfg.enabled:
        return None
    try:
        return AlternationFilter(cfg.joints)
    except ValueError as error:
        raise ConfigError(f"gesture.alternation_filter: {error}") from None
