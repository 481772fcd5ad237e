"""Random experiment directories in the layout of the official MIBURI release, at any size.

The key names and shapes below follow the release's checkpoint format (docs/reference_facts.md §4) and are
checked against the reference's own key lists by tests/test_convert_miburi.py where those lists are present; they
are independent of our own models, so converting such a directory is a real test of the converter. Used by the
tests and by `python -m gesture.release.synthetic OUT [--full-size]` (a full-size random release to time the
converter and the runtime on).

    root/
      config.yaml, speaker_id_to_index.json
      tokens_idle_slices/idle_{upper,face}_tokens_slices.npz     key "0": (1, levels, T)
      checkpoints/glm.safetensors                                 bf16, buffers included
      codecs/codec_{upper,lower,face}.safetensors                 fp32
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml
from safetensors.torch import save_file

from ecas.core.body import REGIONS
from ecas.core.spec import MOSHI_SPEC
from gesture.body.regions import REGION_DIMS
from gesture.codec.config import CodecConfig
from gesture.lm.config import LMConfig

Layout = dict[str, tuple[int, ...]]


_CODEC = CodecConfig()  # our configs' defaults are the reference's sizes
_LM = LMConfig()


@dataclass(frozen=True)
class ReferenceSizes:
    """Every size of a release; the defaults are the reference's, read from our own configs' defaults."""

    latent: int = _CODEC.latent_dim
    n_filters: int = _CODEC.n_filters
    residual_layers: int = _CODEC.residual_layers
    codec_ffn: int = _CODEC.dim_feedforward
    codec_layers: int = _CODEC.regions["upper"].num_layers  # upper/lower; face uses half (`transformer_layers // 2`)
    codec_heads: int = _CODEC.regions["upper"].num_heads
    n_q: dict[str, int] = field(default_factory=lambda: {r: _CODEC.regions[r].n_q for r in REGIONS})
    card: int = _CODEC.codebook_size
    code_dim: int = _CODEC.codebook_dim
    d: int = _LM.d_model
    temporal_layers: int = _LM.temporal_layers
    temporal_heads: int = _LM.temporal_heads
    depth_layers: int = _LM.depth_layers
    depth_heads: int = _LM.depth_heads
    ffn_hidden: int = _LM.ffn_hidden
    n_speakers: int = _LM.n_speakers
    text_vocab: int = MOSHI_SPEC.text_vocab
    audio_card: int = MOSHI_SPEC.audio_card
    embed_dim: int = MOSHI_SPEC.embed_dim
    n_audio: int = MOSHI_SPEC.n_audio_codebooks

    @property
    def n_levels(self) -> int:
        return sum(self.n_q.values())

    def codec_layer_count(self, region: str) -> int:
        return self.codec_layers // 2 if region == "face" else self.codec_layers


def _weight_norm_conv(prefix: str, c_out: int, c_in: int, kernel: int) -> Layout:
    return {
        f"{prefix}.bias": (c_out,),
        f"{prefix}.weight_g": (c_out, 1, 1),
        f"{prefix}.weight_v": (c_out, c_in, kernel),
    }


def _codec_transformer(prefix: str, s: ReferenceSizes, layers: int) -> Layout:
    out: Layout = {}
    for n in range(layers):
        p = f"{prefix}.transformer.layers.{n}"
        out.update(
            {
                f"{p}.self_attn.out_projs.0.weight": (s.latent, s.latent),
                f"{p}.self_attn.in_projs.0.weight": (3 * s.latent, s.latent),
                f"{p}.norm1.weight": (s.latent,),
                f"{p}.norm1.bias": (s.latent,),
                f"{p}.norm2.weight": (s.latent,),
                f"{p}.norm2.bias": (s.latent,),
                f"{p}.linear1.weight": (s.codec_ffn, s.latent),
                f"{p}.linear2.weight": (s.latent, s.codec_ffn),
                f"{p}.layer_scale_1.scale": (s.latent,),
                f"{p}.layer_scale_2.scale": (s.latent,),
            }
        )
    return out


def _residual_blocks(prefix: str, first_index: int, s: ReferenceSizes) -> Layout:
    out: Layout = {}
    hidden = s.n_filters // 2
    for i in range(s.residual_layers):
        p = f"{prefix}.model.{first_index + i}.block"
        out.update(_weight_norm_conv(f"{p}.1.conv.conv", hidden, s.n_filters, 3))
        out.update(_weight_norm_conv(f"{p}.3.conv.conv", s.n_filters, hidden, 1))
    return out


def codec_layout(s: ReferenceSizes, region: str) -> Layout:
    """Keys and shapes of one reference codec checkpoint."""
    nfeats, r = REGION_DIMS[region], s.residual_layers
    out = _weight_norm_conv("seanet_encoder.model.0.conv.conv", s.n_filters, nfeats, 7)
    out.update(_residual_blocks("seanet_encoder", 1, s))
    out.update(_weight_norm_conv(f"seanet_encoder.model.{r + 2}.conv.conv", 2 * s.n_filters, s.n_filters, 4))
    out.update(_weight_norm_conv(f"seanet_encoder.model.{r + 4}.conv.conv", s.latent, 2 * s.n_filters, 7))
    out.update(_codec_transformer("transformer_encoder", s, s.codec_layer_count(region)))
    out.update(_codec_transformer("transformer_decoder", s, s.codec_layer_count(region)))
    out.update(_weight_norm_conv("seanet_decoder.model.0.conv.conv", 2 * s.n_filters, s.latent, 7))
    tr = "seanet_decoder.model.2.convtr.convtr"  # weight (C_in, C_out, K): g is per *input* channel
    out.update(
        {
            f"{tr}.bias": (s.n_filters,),
            f"{tr}.weight_g": (2 * s.n_filters, 1, 1),
            f"{tr}.weight_v": (2 * s.n_filters, s.n_filters, 4),
        }
    )
    out.update(_residual_blocks("seanet_decoder", 3, s))
    out.update(_weight_norm_conv(f"seanet_decoder.model.{r + 4}.conv.conv", nfeats, s.n_filters, 7))
    out.update(
        {
            "quantizer.input_proj.weight": (s.code_dim, s.latent, 1),
            "quantizer.output_proj.weight": (s.latent, s.code_dim, 1),
        }
    )
    for i in range(s.n_q[region]):
        out.update(_ema_codebook(f"quantizer.vq.layers.{i}", s))
    return out


def _ema_codebook(prefix: str, s: ReferenceSizes) -> Layout:
    return {
        f"{prefix}._codebook._initialized": (1,),
        f"{prefix}._codebook.cluster_usage": (s.card,),
        f"{prefix}._codebook.embedding_sum": (s.card, s.code_dim),
    }


def _glm_layer(prefix: str, s: ReferenceSizes, copies: int | None) -> Layout:
    """A temporal layer (copies None: no per-step index) or a depth layer (`copies` per-step weights)."""
    d, steps = s.d, [""] if copies is None else [f".{i}" for i in range(copies)]
    out: Layout = {}
    for attn in ("self_attn", "cross_attns.0", "cross_attns.1"):
        for proj in ("in_projs", "key_projs", "val_projs", "out_projs"):
            out.update({f"{prefix}.{attn}.{proj}.{i}.weight": (d, d) for i in range(copies or 1)})
    for gate in ("gating", "ca_gating"):
        for step in steps:
            out.update(
                {
                    f"{prefix}.{gate}{step}.linear_in.weight": (2 * s.ffn_hidden, d),
                    f"{prefix}.{gate}{step}.linear_out.weight": (d, s.ffn_hidden),
                }
            )
    for norm in ("norm1", "norm2", "norm3.0", "norm3.1"):
        out.update({f"{prefix}.{norm}.weight": (d,), f"{prefix}.{norm}.bias": (d,)})
    out.update({f"{prefix}.memory_projs.0.weight": (d, 2 * d), f"{prefix}.memory_projs.0.bias": (d,)})
    return out


def glm_layout(s: ReferenceSizes, face_va: bool) -> Layout:
    """Keys and shapes of the reference GLM checkpoint (`face_va`: with the optional `vad_face_proj`)."""
    d, depth, vocab = s.d, s.n_levels - 1, s.card + 1
    out: Layout = {f"audio_procemb.{i}.weight": (s.audio_card, s.embed_dim) for i in range(s.n_audio)}
    out["text_procemb.weight"] = (s.text_vocab, s.embed_dim)
    for i in range(s.n_levels):
        out.update(_ema_codebook(f"gesture_codec_layers.{i}", s))
        out.update(
            {
                f"temporal_gemb.{i}.weight": (s.card, s.code_dim),
                f"temporal_gemb.{i}.pad_embedding.weight": (1, s.code_dim),
                f"temporal_gproj.{i}.weight": (d, s.code_dim),
            }
        )
    out["spk_tempemb.weight"] = (s.n_speakers, d)
    for n in range(s.temporal_layers):
        out.update(_glm_layer(f"temporal_transformer.layers.{n}", s, None))
    out.update({"out_norm.weight": (d,), "out_norm.bias": (d,), "temporal_classifier.weight": (vocab, d)})
    for k in range(depth):
        out.update(
            {
                f"depformer_in.{k}.weight": (d, d),
                f"spk_depemb.{k}.weight": (s.n_speakers, d),
                f"depformer_gemb.{k}.weight": (s.card, s.code_dim),
                f"depformer_gemb.{k}.pad_embedding.weight": (1, s.code_dim),
                f"depformer_gproj.{k}.weight": (d, s.code_dim),
                f"depformer_classifier.{k}.weight": (vocab, d),
            }
        )
    for n in range(s.depth_layers):
        out.update(_glm_layer(f"depth_transformer.layers.{n}", s, depth))
    for name in ("temp_condproj", "dep_condproj"):
        out.update(
            {f"{name}.{i}.{p}": shape for i in range(2) for p, shape in (("weight", (d, s.embed_dim)), ("bias", (d,)))}
        )
    va_in = d + vocab if face_va else d
    if face_va:
        out.update({"vad_face_proj.weight": (vocab, s.n_q["face"] * vocab), "vad_face_proj.bias": (vocab,)})
    out.update(
        {
            "vad_predictor.0.weight": (va_in,),
            "vad_predictor.0.bias": (va_in,),
            "vad_predictor.1.weight": (d, va_in),
            "vad_predictor.1.bias": (d,),
            "vad_predictor.3.weight": (128, d),
            "vad_predictor.3.bias": (128,),
            "vad_predictor.5.weight": (d, 128),
            "vad_predictor.5.bias": (d,),
            "vad_predictor.7.weight": (1, d),
            "vad_predictor.7.bias": (1,),
        }
    )
    return out


def reference_config(s: ReferenceSizes, face_va: bool) -> dict:
    """The fields of the experiment's `config.yaml` that a loader reads (plus a few it does not)."""
    return {
        "transformer_heads": s.codec_heads,
        "transformer_layers": s.codec_layers,
        "convblock_layers": 2,
        "gestureformer_heads": s.temporal_heads,
        "gestureformer_layers": s.temporal_layers,
        "gestureformer_depformer_heads": s.depth_heads,
        "gestureformer_depformer_layers": s.depth_layers,
        "num_temp_classifiers": 1,
        "vad_guidance": False,
        "vad_use_face_logits": face_va,
        "textaudio_emb_freeze": True,
        "num_frames": 250,
        "frame_chunk_size": 2,
        "motion_fps": 25,
        "lr": 1e-4,
        "batch_size": 128,
    }


def random_tensors(layout: Layout, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Plausible random values: small weights, norms near 1, positive EMA usage (a few zero / tiny ones)."""
    out = {}
    for key, shape in layout.items():
        if key.endswith("_initialized"):
            value = torch.ones(shape)
        elif key.endswith("cluster_usage"):
            value = torch.rand(shape, generator=generator) * 4 + 0.5
            value[:2] = torch.tensor([0.0, 1e-7])  # max(usage, 1e-5) matters for these two codes
        elif key.endswith("embedding_sum"):
            value = torch.randn(shape, generator=generator)
            value[:2] *= 1e-6
        elif key.endswith("weight_g"):
            value = torch.rand(shape, generator=generator) + 0.5
        elif ".norm" in key or key.startswith(("out_norm", "vad_predictor.0")):
            value = (1.0 if key.endswith("weight") else 0.0) + 0.1 * torch.randn(shape, generator=generator)
        elif key.endswith("scale"):
            value = torch.full(shape, 0.1) + 0.01 * torch.randn(shape, generator=generator)
        else:
            fan_in = shape[1] * (shape[2] if len(shape) > 2 else 1) if len(shape) > 1 else 16
            value = torch.randn(shape, generator=generator) / fan_in**0.5
        out[key] = value
    return out


@dataclass
class ExperimentFiles:
    root: Path
    glm: Path
    codecs: dict[str, Path]


def write_experiment(
    root: Path,
    sizes: ReferenceSizes = ReferenceSizes(),
    *,
    seed: int = 0,
    face_va: bool = False,
    glm_prefix: str = "module.",
    idle_steps: int = 30,
    fill: Callable[[str, dict[str, torch.Tensor]], None] | None = None,
) -> ExperimentFiles:
    """Write a random release into `root`. The GLM gets the codecs' codebooks (as training copies them), a
    `glm_prefix` on its keys and bf16 storage; `fill(name, tensors)` may overwrite values before saving."""
    root = Path(root)
    generator = torch.Generator().manual_seed(seed)
    codecs = {region: random_tensors(codec_layout(sizes, region), generator) for region in REGIONS}
    glm = random_tensors(glm_layout(sizes, face_va), generator)
    levels = [
        codecs[r][f"quantizer.vq.layers.{i}._codebook.{name}"]
        for r in REGIONS
        for i in range(sizes.n_q[r])
        for name in ("cluster_usage", "embedding_sum")
    ]
    for level in range(sizes.n_levels):
        glm[f"gesture_codec_layers.{level}._codebook.cluster_usage"] = levels[2 * level].clone()
        glm[f"gesture_codec_layers.{level}._codebook.embedding_sum"] = levels[2 * level + 1].clone()
    if fill is not None:
        for region in REGIONS:
            fill(f"codec_{region}", codecs[region])
        fill("glm", glm)
    paths = {region: root / "codecs" / f"codec_{region}.safetensors" for region in REGIONS}
    for region, path in paths.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        save_file({k: v.float().contiguous() for k, v in codecs[region].items()}, str(path))
    glm_path = root / "checkpoints" / "glm.safetensors"
    glm_path.parent.mkdir(parents=True, exist_ok=True)
    save_file({glm_prefix + k: v.to(torch.bfloat16).contiguous() for k, v in glm.items()}, str(glm_path))
    (root / "config.yaml").write_text(yaml.safe_dump(reference_config(sizes, face_va), sort_keys=False))
    speakers = ["scott", "stewart", "lawrence", "solomon", "wayne", "sophie", "carla"]
    (root / "speaker_id_to_index.json").write_text(
        json.dumps({name: (i + 2) % sizes.n_speakers for i, name in enumerate(speakers)}, indent=1)
    )
    idle_dir = root / "tokens_idle_slices"
    idle_dir.mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    for region in ("upper", "face"):
        tokens = rng.integers(0, sizes.card, (1, sizes.n_q[region], idle_steps))
        np.savez(idle_dir / f"idle_{region}_tokens_slices.npz", **{"0": tokens})
    return ExperimentFiles(root, glm_path, paths)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="ecas fake-release", description="Write a random release in the official MIBURI layout."
    )
    p.add_argument("out", type=Path)
    p.add_argument("--face-va", action="store_true", help="include the optional vad_face_proj head")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    files = write_experiment(args.out, ReferenceSizes(), seed=args.seed, face_va=args.face_va)
    print(f"wrote {files.root} (GLM {files.glm}, codecs in {files.root / 'codecs'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
