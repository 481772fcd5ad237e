"""The gesture language model (docs/reference_facts.md §3): a temporal transformer over 80 ms steps and a depth
(kinematic) transformer over the 20 codebook levels of a step, conditioned on a text token and 8 audio codes.

This module is stateless: `forward` is the teacher-forced full-sequence pass used in training and as the
reference of the streaming step path (`gesture.lm.stepper.LMStepper`). Attribute names equal the reference
checkpoint keys (`state_dict_keys/glm_vfl*.tsv`), so a converter is a pure key mapping.

Choices where the facts leave room: the depth inputs `depformer_in[k]` read the temporal output after `out_norm`
(the normalised state the temporal classifier reads); the VA head reads it before `out_norm` (the head starts with
its own LayerNorm); a decoder layer runs self-attention, then the cross-attention block, then the gated FFN.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ecas.core.spec import ConditionSpec
from gesture.lm.config import LMConfig
from gesture.lm.embeddings import GestureEmbedding, check_token_range, embed_or_zero
from gesture.lm.layers import LAYER_NORM_EPS, DepthLayer, TemporalLayer
from gesture.nn.rope import RotaryEmbedding

EMA_USAGE_EPS = 1e-5


@dataclass
class LMOutput:
    logits: torch.Tensor  # (B, T, K, card + 1): level 0 from the temporal classifier, 1..K-1 from the depth
    temporal: torch.Tensor  # (B, T, d) temporal transformer output before `out_norm`
    va_logit: torch.Tensor | None  # (B, T) voice-activity logit, None without a VA head


class LayerStack(nn.Module):
    def __init__(self, layers: list[nn.Module]) -> None:
        super().__init__()
        self.layers = nn.ModuleList(layers)


class EmaCodebook(nn.Module):
    """A frozen codec codebook in the EMA storage of the codecs (`_initialized`, `cluster_usage`, `embedding_sum`)."""

    def __init__(self, card: int, dim: int) -> None:
        super().__init__()
        self.register_buffer("_initialized", torch.ones(1))
        self.register_buffer("cluster_usage", torch.ones(card))
        self.register_buffer("embedding_sum", torch.zeros(card, dim))

    def vectors(self) -> torch.Tensor:
        """(card, dim) codebook vectors = embedding_sum / max(cluster_usage, eps)."""
        return self.embedding_sum / self.cluster_usage.clamp_min(EMA_USAGE_EPS)[:, None]


class CodecCodebookLevel(nn.Module):
    def __init__(self, card: int, dim: int) -> None:
        super().__init__()
        self._codebook = EmaCodebook(card, dim)


def shift_history(tokens: torch.Tensor) -> torch.Tensor:
    """Temporal input of step t = tokens of step t−1, and −1 at t = 0; (B, K, T) -> (B, K, T)."""
    empty = torch.full_like(tokens[..., :1], -1)
    return torch.cat([empty, tokens[..., :-1]], dim=-1)


class GestureLM(nn.Module):
    """`GestureLM(sizes, spec)`; see the module docstring."""

    def __init__(self, sizes: LMConfig, spec: ConditionSpec) -> None:
        super().__init__()
        self.sizes, self.spec = sizes, spec
        d, card, levels, depth = sizes.d_model, sizes.card, sizes.n_levels, sizes.n_depth
        self.audio_procemb = nn.ModuleList(
            [nn.Embedding(spec.audio_card, spec.embed_dim) for _ in range(spec.n_audio_codebooks)]
        )
        self.text_procemb = nn.Embedding(spec.text_vocab, spec.embed_dim)
        self.gesture_codec_layers = nn.ModuleList([CodecCodebookLevel(card, sizes.code_dim) for _ in range(levels)])
        self.temporal_gemb = nn.ModuleList([GestureEmbedding(card, sizes.code_dim) for _ in range(levels)])
        self.temporal_gproj = nn.ModuleList([nn.Linear(sizes.code_dim, d, bias=False) for _ in range(levels)])
        self.spk_tempemb = nn.Embedding(sizes.n_speakers, d)
        temporal_rope = RotaryEmbedding(d // sizes.temporal_heads, sizes.rope_period)
        self.temporal_transformer = LayerStack(
            [
                TemporalLayer(
                    d,
                    sizes.temporal_heads,
                    sizes.ffn_hidden,
                    sizes.self_context_steps,
                    sizes.cross_context_steps,
                    temporal_rope,
                    sizes.dropout,
                )
                for _ in range(sizes.temporal_layers)
            ]
        )
        self.out_norm = nn.LayerNorm(d, eps=LAYER_NORM_EPS)
        self.temporal_classifier = nn.Linear(d, card + 1, bias=False)
        self.depformer_in = nn.ModuleList([nn.Linear(d, d, bias=False) for _ in range(depth)])
        self.spk_depemb = nn.ModuleList([nn.Embedding(sizes.n_speakers, d) for _ in range(depth)])
        self.depformer_gemb = nn.ModuleList([GestureEmbedding(card, sizes.code_dim) for _ in range(depth)])
        self.depformer_gproj = nn.ModuleList([nn.Linear(sizes.code_dim, d, bias=False) for _ in range(depth)])
        depth_rope = RotaryEmbedding(d // sizes.depth_heads, sizes.rope_period)
        self.depth_transformer = LayerStack(
            [
                DepthLayer(d, sizes.depth_heads, sizes.ffn_hidden, depth, depth_rope, sizes.dropout)
                for _ in range(sizes.depth_layers)
            ]
        )
        self.depformer_classifier = nn.ModuleList([nn.Linear(d, card + 1, bias=False) for _ in range(depth)])
        self.temp_condproj = nn.ModuleList([nn.Linear(spec.embed_dim, d) for _ in range(2)])  # audio, text
        self.dep_condproj = nn.ModuleList([nn.Linear(spec.embed_dim, d) for _ in range(2)])
        if sizes.va_use_face_logits:
            self.vad_face_proj = nn.Linear(sizes.n_face * (card + 1), card + 1)
        if sizes.va_head:
            va_in = d + (card + 1 if sizes.va_use_face_logits else 0)
            self.vad_predictor = nn.Sequential(
                nn.LayerNorm(va_in, eps=LAYER_NORM_EPS),
                nn.Linear(va_in, d),
                nn.GELU(),
                nn.Linear(d, 128),
                nn.GELU(),
                nn.Linear(128, d),
                nn.GELU(),
                nn.Linear(d, 1),
            )
        self.register_buffer("cross_masked", self._cross_masked_positions(), persistent=False)

    def _cross_masked_positions(self) -> torch.Tensor:
        """(n_depth,) bool: depth position k predicts level k+1; lower-body levels see no condition."""
        lower = set(self.sizes.lower_levels) if self.sizes.mask_lower_cross_attn else set()
        return torch.tensor([k + 1 in lower for k in range(self.sizes.n_depth)])

    # ----- conditioning -------------------------------------------------------------------------------------
    def condition_embeddings(self, text: torch.Tensor, audio: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """text (B, T), audio (B, Q, T) -> (audio sum, text) embeddings, each (B, T, embed_dim); −1 gives zero."""
        check_token_range(text, self.spec.text_vocab, "text tokens")
        check_token_range(audio, self.spec.audio_card, "audio codes")
        if audio.shape[1] != self.spec.n_audio_codebooks:
            raise ValueError(f"audio codes: expected {self.spec.n_audio_codebooks} codebooks, got {audio.shape[1]}")
        audio_sum = sum(embed_or_zero(table, audio[:, q]) for q, table in enumerate(self.audio_procemb))
        return audio_sum, embed_or_zero(self.text_procemb, text)

    # ----- forward ------------------------------------------------------------------------------------------
    def forward(
        self,
        tokens: torch.Tensor,
        text: torch.Tensor,
        audio: torch.Tensor,
        speaker: torch.Tensor,
        history: torch.Tensor | None = None,
        offset: int = 0,
    ) -> LMOutput:
        """Teacher-forced pass. tokens (B, K, T): the step's own tokens (depth inputs; may hold pad);
        history (B, K, T): temporal inputs, default `shift_history(tokens)`; text (B, T); audio (B, Q, T);
        speaker (B,); offset: absolute step index of t = 0 (RoPE positions)."""
        check_token_range(tokens, self.sizes.card + 1, "gesture tokens")
        history = shift_history(tokens) if history is None else history
        audio_sum, text_emb = self.condition_embeddings(text, audio)
        temporal = self.temporal_forward(history, audio_sum, text_emb, speaker, offset)  # (B, T, d)
        level0 = self.temporal_classifier(self.out_norm(temporal))  # (B, T, card+1)
        depth_logits = self.depth_forward(self.out_norm(temporal), tokens, audio_sum, text_emb, speaker)
        logits = torch.cat([level0[:, :, None], depth_logits], dim=2)  # (B, T, K, card+1)
        return LMOutput(logits, temporal, self.va_logit(temporal, logits) if self.sizes.va_head else None)

    def gesture_input(self, history: torch.Tensor, speaker: torch.Tensor) -> torch.Tensor:
        """history (B, K, T) -> (B, T, d): sum over levels of gproj(gemb(token)) + speaker embedding."""
        x = sum(proj(emb(history[:, k])) for k, (emb, proj) in enumerate(zip(self.temporal_gemb, self.temporal_gproj)))
        return x + self.spk_tempemb(speaker)[:, None]

    def temporal_forward(
        self,
        history: torch.Tensor,
        audio_sum: torch.Tensor,
        text_emb: torch.Tensor,
        speaker: torch.Tensor,
        offset: int = 0,
    ) -> torch.Tensor:
        x = self.gesture_input(history, speaker)  # (B, T, d)
        audio_memory, text_memory = self.temp_condproj[0](audio_sum), self.temp_condproj[1](text_emb)
        positions = torch.arange(offset, offset + x.shape[1], device=x.device)
        for layer in self.temporal_transformer.layers:
            x = layer(x, audio_memory, text_memory, positions)
        return x

    def depth_forward(
        self,
        temporal_normed: torch.Tensor,
        tokens: torch.Tensor,
        audio_sum: torch.Tensor,
        text_emb: torch.Tensor,
        speaker: torch.Tensor,
    ) -> torch.Tensor:
        """All depth positions of all steps at once -> logits (B, T, K-1, card+1) of levels 1..K-1."""
        batch, steps, d = temporal_normed.shape
        depth = self.sizes.n_depth
        inputs = tokens[:, :depth].transpose(1, 2)  # (B, T, S)
        z = torch.stack(
            [
                self.depformer_in[k](temporal_normed)
                + self.depformer_gproj[k](self.depformer_gemb[k](inputs[..., k]))
                + self.spk_depemb[k](speaker)[:, None]
                for k in range(depth)
            ],
            dim=2,
        )  # (B, T, S, d)
        z = z.flatten(0, 1)  # (B*T, S, d)
        audio_memory = self.dep_condproj[0](audio_sum).flatten(0, 1)[:, None]  # (B*T, 1, d)
        text_memory = self.dep_condproj[1](text_emb).flatten(0, 1)[:, None]
        key_valid = (inputs != self.sizes.pad_token).flatten(0, 1)  # (B*T, S)
        for layer in self.depth_transformer.layers:
            z = layer(z, audio_memory, text_memory, key_valid, self.cross_masked)
        logits = torch.stack([self.depformer_classifier[k](z[:, k]) for k in range(depth)], dim=1)  # (B*T, S, V)
        return logits.unflatten(0, (batch, steps))

    def va_logit(self, temporal: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """temporal (B, T, d), logits (B, T, K, V) -> (B, T) voice-activity logit."""
        features = temporal
        if self.sizes.va_use_face_logits:
            face = logits[:, :, self.sizes.face_levels.start :].flatten(2)  # (B, T, n_face*V)
            features = torch.cat([temporal, self.vad_face_proj(face)], dim=-1)
        return self.vad_predictor(features).squeeze(-1)

    # ----- codebooks ----------------------------------------------------------------------------------------
    def codebook_vectors(self, level: int) -> torch.Tensor:
        """(card, code_dim) vectors of the codec codebook behind level `level`."""
        return self.gesture_codec_layers[level]._codebook.vectors()

    def set_codec_codebooks(self, vectors: list[torch.Tensor], init_embeddings: bool = True) -> None:
        """Store the 20 frozen codec codebooks (card, code_dim) and, for a fresh model, initialise the temporal and
        depth gesture tables from them (docs/reference_facts.md §3)."""
        if len(vectors) != self.sizes.n_levels:
            raise ValueError(f"expected {self.sizes.n_levels} codebooks, got {len(vectors)}")
        with torch.no_grad():
            for level, vec in enumerate(vectors):
                book = self.gesture_codec_layers[level]._codebook
                book.embedding_sum.copy_(vec)
                book.cluster_usage.fill_(1.0)
                if init_embeddings:
                    self.temporal_gemb[level].weight.copy_(vec)
                    if level < self.sizes.n_depth:
                        self.depformer_gemb[level].weight.copy_(vec)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
