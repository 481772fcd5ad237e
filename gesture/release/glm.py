"""The release gesture language model -> our `GestureLM` (docs/reference_facts.md §3, §4, §7).

Our model keeps the reference's parameter names, so the tensors load unchanged once the `module.`/`m.`
prefix is stripped and bf16 is cast to fp32. Sizes come from the shapes (width, card, code size, speakers,
layers, FFN width, conditioning vocabularies) and from `config.yaml` (heads, which shapes cannot give).

Keys that are loaded but never used at inference: the depth cross-attention key/value copies 1..18 (we use
the trained index-0 projections at every depth position, section 9) and `gesture_codec_layers.*` (the frozen
codec codebooks; the converter checks them against the codecs). The optional face-logit voice-activity head
(`vad_face_proj`, a training-only auxiliary) is detected and dropped together with the `vad_predictor` that
reads it; without it the plain `vad_predictor` is kept and feeds the runtime's voice-activity output.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ecas.core.spec import ConditionSpec
from gesture.lm.config import LMConfig
from gesture.lm.model import GestureLM
from gesture.release.codecs import codebook_vectors
from gesture.release.keys import match_keys, state_shapes
from gesture.release.source import ExperimentConfig, ReleaseError, SourceCheckpoint

CONDITION_NAME = "moshi"
FACE_VA_KEY = "vad_face_proj.weight"
CODEBOOK_RTOL = 2e-2  # the GLM stores its codebook copies in bf16 (8 significant bits)


@dataclass
class GlmLayout:
    """What the converter read from a GLM checkpoint and its config."""

    sizes: LMConfig
    spec: ConditionSpec
    ignored: dict[str, str] = field(default_factory=dict)  # source key -> why it is dropped
    unused: dict[str, str] = field(default_factory=dict)  # pattern -> why it is loaded but unused


def _heads(config: ExperimentConfig, name: str, d: int) -> int:
    heads = config.require_int(name)
    if heads < 1 or d % heads or (d // heads) % 2:
        raise ReleaseError(
            f"{config.path}: field {name!r} = {heads} does not split the GLM width {d} into heads of even size"
        )
    return heads


def _check_layers(config: ExperimentConfig, name: str, found: int, source: SourceCheckpoint) -> None:
    value = config.get(name)
    if isinstance(value, int) and not isinstance(value, bool) and value != found:
        raise ReleaseError(f"{source.path}: has {found} layers, but {config.path} field {name!r} = {value}")


def read_glm_layout(source: SourceCheckpoint, config: ExperimentConfig, region_levels: dict[str, int]) -> GlmLayout:
    """Sizes and condition spec of the checkpoint; `region_levels` are the codecs' n_q (upper, lower, face)."""
    n_speakers, d = source.shape("spk_tempemb.weight")
    card, code_dim = source.shape("temporal_gemb.0.weight")
    levels = source.count("temporal_gemb.{}.weight")
    if levels != sum(region_levels.values()):
        raise ReleaseError(
            f"{source.path}: has {levels} gesture levels (temporal_gemb.*), but the codecs have "
            f"{region_levels} codebooks ({sum(region_levels.values())} in all)"
        )
    temporal_layers = source.count("temporal_transformer.layers.{}.norm1.weight")
    depth_layers = source.count("depth_transformer.layers.{}.norm1.weight")
    _check_layers(config, "gestureformer_layers", temporal_layers, source)
    _check_layers(config, "gestureformer_depformer_layers", depth_layers, source)
    classifiers = config.get("num_temp_classifiers", 1)
    if classifiers != 1:
        raise ReleaseError(f"{config.path}: field 'num_temp_classifiers' = {classifiers}; only 1 is supported")
    face_va = FACE_VA_KEY in source.tensors
    has_va = "vad_predictor.7.weight" in source.tensors
    sizes = LMConfig(
        d_model=d,
        temporal_layers=temporal_layers,
        temporal_heads=_heads(config, "gestureformer_heads", d),
        depth_layers=depth_layers,
        depth_heads=_heads(config, "gestureformer_depformer_heads", d),
        ffn_hidden=source.shape("temporal_transformer.layers.0.gating.linear_out.weight")[1],
        n_upper=region_levels["upper"],
        n_lower=region_levels["lower"],
        n_face=region_levels["face"],
        card=card,
        code_dim=code_dim,
        n_speakers=n_speakers,
        va_head=has_va and not face_va,
        va_use_face_logits=False,
    )
    text_vocab, embed_dim = source.shape("text_procemb.weight")
    spec = ConditionSpec(
        name=CONDITION_NAME,
        text_vocab=text_vocab,
        audio_card=source.shape("audio_procemb.0.weight")[0],
        embed_dim=embed_dim,
        n_audio_codebooks=source.count("audio_procemb.{}.weight"),
    )
    ignored = {}
    if face_va:
        reason = "face-logit voice-activity head (training-only auxiliary), dropped"
        ignored = {k: reason for k in source.tensors if k.startswith(("vad_face_proj.", "vad_predictor."))}
    depth_copies = f"depth_transformer.layers.*.cross_attns.*.{{key,val}}_projs.1-{sizes.n_depth - 1}"
    unused = {
        depth_copies: "kept; every depth position uses the trained index-0 projections (docs/reference_facts.md §7)",
        "gesture_codec_layers.*": "kept; frozen codec codebooks, checked against the codecs",
    }
    return GlmLayout(sizes, spec, ignored, unused)


def convert_glm(source: SourceCheckpoint, layout: GlmLayout) -> GestureLM:
    """Our GestureLM holding the source tensors (fp32), strictly checked. Built on the meta device and filled
    by assignment, so the full-size model is never allocated twice."""
    with torch.device("meta"):
        model = GestureLM(layout.sizes, layout.spec)
    state = match_keys(source, state_shapes(model), layout.ignored)
    model.load_state_dict(state, strict=True, assign=True)
    return model


def check_codebooks(source: SourceCheckpoint, codec_books: list[tuple[str, torch.Tensor]]) -> float:
    """The GLM's frozen copies must be the codecs' codebooks (within bf16 rounding): otherwise its tokens would
    decode through the wrong codes. Returns the largest relative difference."""
    worst = 0.0
    for level, (name, expected) in enumerate(codec_books):
        actual = codebook_vectors(source, f"gesture_codec_layers.{level}")
        scale = expected.abs().amax(dim=1, keepdim=True).clamp_min(1e-12)  # (card, 1): per-code magnitude
        error = float(((actual - expected).abs() / scale).max())
        if error > CODEBOOK_RTOL:
            raise ReleaseError(
                f"{source.path}: key 'gesture_codec_layers.{level}._codebook.embedding_sum' does not "
                f"match the codec codebook {name} (relative difference {error:.3g}): these codecs "
                f"are not the ones this GLM was trained with"
            )
        worst = max(worst, error)
    return worst
