"""Build the streaming gesture generator of a `gesture:` config section: checkpoints, spec check, sampling options
and the runtime layers. The engine (`gesture.engine`) and the gesture stage (`gesture.process`, through the engine)
build theirs here, so they run the same generator.
"""

from __future__ import annotations

from ecas.core.config import ConfigError
from ecas.core.timing import MOTION_FPS
from gesture.config import GestureConfig
from gesture.generator import GestureGenerator, level_slices
from gesture.layers import LayerEnv, build_layers
from gesture.lm.checkpoint import load_lm
from gesture.lm.codecs import load_codecs
from gesture.nn.weights import UnsupportedFormError, require_fast_form


def build_generator(cfg: GestureConfig, seed: int) -> GestureGenerator:
    """The generator of a `gesture:` section: checkpoints, spec check, sampling options, runtime layers."""
    if cfg.lm_checkpoint is None:
        raise ConfigError("gesture.lm_checkpoint: required (a directory written by ecas train-lm)")
    if cfg.codec_checkpoints is None:
        raise ConfigError("gesture.codec_checkpoints: required (a directory with upper/, lower/ and face/ codecs)")
    try:
        require_fast_form(cfg.dtype, "gesture.dtype", cfg.dtype_fallback, "gesture.dtype_fallback")
    except UnsupportedFormError as error:
        raise ConfigError(str(error)) from None
    lm = load_lm(cfg.lm_checkpoint, cfg.dialogue_spec)
    codecs = load_codecs(cfg.codec_checkpoints)
    layers = build_layers(cfg.layers, LayerEnv(seed=seed, fps=MOTION_FPS, levels=level_slices(lm)))
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
        layers=layers,
        speaking_rms=cfg.speaking_rms,
        initial_translation=cfg.initial_translation,
    )
