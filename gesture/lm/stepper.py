"""The cached, step-by-step form of `GestureLM` for streaming generation on CPU.

`LMStepper(model, guided, dtype)` copies the model's weights once into fused, precomputed forms, then runs one
80 ms step as `begin_step(history, text, audio)` (temporal transformer, level-0 logits) followed by
`depth_logits(k, token_k)` for k = 0..K-2 (the depth transformer, one level at a time). Row 0 of every batch is
the conditioned stream; with `guided` a row 1 runs the same history with the empty condition (CFG's null half).

Exact rewrites used (all proved against `GestureLM.forward` in tests/test_lm_stepper.py):
- embeddings followed by a linear = a lookup in a projected table (the sum of 8 audio lookups + one bias);
- the depth cross-attention has one memory token, so its softmax is 1 and its output is out_proj(val_proj(m)):
  with `memory_projs` folded in, the pre-activation is one (d, 2d) matrix per position applied to [m_audio, m_text];
- the null half's memory is a constant (the condition projections' biases), so its cross-attention block output is
  a per-layer (temporal) or per-layer-and-position (depth) constant; masked lower-body depth rows are constants too;
- the temporal cross-attention out_projs and memory_projs fold into one (d, 2d) matrix.
Weights of the matrix products are stored in `dtype` (bfloat16 halves the memory traffic that bounds CPU speed);
activations, norms, softmax and caches stay float32. Nothing allocated here grows with the session length.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gesture.lm.embeddings import table_index
from gesture.lm.layers import LAYER_NORM_EPS, DepthLayer, TemporalLayer
from gesture.lm.model import GestureLM
from gesture.lm.packed import gated_ffn, linear, pack_weight
from gesture.nn.attention import attention_mask
from gesture.nn.kv_cache import RingKVCache
from gesture.nn.rope import apply_rope
from gesture.nn.streaming import StreamingState

F32 = torch.float32


def _ffn(x: torch.Tensor, w_in, w_out) -> torch.Tensor:
    return gated_ffn(x, w_in, w_out)


def _rotate(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """RoPE on interleaved pairs of x (..., Dh) with precomputed cos/sin (Dh/2,) of one position."""
    pairs = x.unflatten(-1, (-1, 2))  # (..., Dh/2, 2)
    real, imag = pairs[..., 0], pairs[..., 1]
    return torch.stack((real * cos - imag * sin, real * sin + imag * cos), dim=-1).flatten(-2)


def _rotate_rows(weight: torch.Tensor, position: int, freqs: torch.Tensor, heads: int) -> torch.Tensor:
    """(d, d_in) projection whose outputs are RoPE-rotated at a fixed `position`: rope(W h) = rope(W) h."""
    columns = weight.T.unflatten(-1, (heads, -1)).transpose(0, 1)[None]  # (1, H, d_in, Dh)
    rotated = apply_rope(columns, torch.full((weight.shape[1],), position), freqs)
    return rotated[0].transpose(0, 1).flatten(1).T  # (d, d_in)


def _attend(q: torch.Tensor, keys: torch.Tensor, values: torch.Tensor, allowed: torch.Tensor) -> torch.Tensor:
    """q (B, H, 1, Dh) over a ring (B, H, C, Dh) with `allowed` (1, C) -> (B, H*Dh)."""
    scores = (q @ keys.transpose(-1, -2)) * q.shape[-1] ** -0.5  # (B, H, 1, C)
    weights = torch.softmax(scores.masked_fill(~allowed, float("-inf")), dim=-1)
    return (weights @ values).flatten(1)


def _norm(x: torch.Tensor, params: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    return F.layer_norm(x, (x.shape[-1],), params[0], params[1], LAYER_NORM_EPS)


def _norm_params(norm: torch.nn.LayerNorm) -> tuple[torch.Tensor, torch.Tensor]:
    return norm.weight.detach().clone(), norm.bias.detach().clone()


@dataclass
class _TemporalWeights:
    norm1: tuple
    norm2: tuple
    norm3: tuple
    qkv: torch.Tensor  # (3d, d)
    out: torch.Tensor  # (d, d)
    q_audio: torch.Tensor
    q_text: torch.Tensor
    mix: torch.Tensor  # (d, 2d) = memory_projs ∘ [out_audio, out_text]
    mix_bias: torch.Tensor
    ca_in: torch.Tensor
    ca_out: torch.Tensor
    ffn_in: torch.Tensor
    ffn_out: torch.Tensor
    null_ca: torch.Tensor  # (d,) cross-attention block output of the null half


@dataclass
class _DepthWeights:
    norm1: tuple
    norm2: tuple
    qkv: list  # per position (3d, d)
    out: list
    ffn_in: list
    ffn_out: list
    ca_in: list
    ca_out: list
    const_ca: torch.Tensor  # (S, d): masked positions (both halves) and the null half
    mix_bias: torch.Tensor


@dataclass
class LMStepState(StreamingState):
    """Per-session state: ring caches of the temporal transformer and the depth scratch of the current step."""

    self_caches: list  # RingKVCache (B, H, self_context, Dh) per temporal layer
    audio_caches: list  # RingKVCache (1, H, cross_context, Dh) per layer: conditioned row only
    text_caches: list
    depth_keys: torch.Tensor  # (L_depth, B, H, S, Dh)
    depth_values: torch.Tensor
    depth_z: torch.Tensor  # (B, S, d) depth inputs without the token embedding
    depth_ca: torch.Tensor  # (L_depth, S, d) cross-attention block output of row 0
    step: int = 0

    def reset(self) -> None:
        for cache in (*self.self_caches, *self.audio_caches, *self.text_caches):
            cache.reset()
        self.depth_keys.zero_()
        self.depth_values.zero_()
        self.step = 0


class LMStepper:
    """Cached step path of a `GestureLM`; see the module docstring."""

    def __init__(self, model: GestureLM, guided: bool, dtype: torch.dtype = F32) -> None:
        self.sizes, self.spec = model.sizes, model.spec
        self.batch = 2 if guided else 1
        self.dtype = dtype
        self.has_va = model.sizes.va_head
        self._va_model = model if self.has_va else None
        with torch.no_grad():
            self._prepare_tables(model)
            self._prepare_temporal(model)
            self._prepare_depth(model)
        self.state = self._new_state()
        self.set_speaker(0)

    # ----- preparation ----------------------------------------------------------------------------------------
    def _cast(self, w: torch.Tensor):
        return pack_weight(w, self.dtype, self.batch)

    def _prepare_tables(self, model: GestureLM) -> None:
        card = self.sizes.card
        self.row_stride = card + 2  # codes, pad, zero row
        self.gesture_table = torch.cat([proj(emb.full_table()) for emb, proj in
                                        zip(model.temporal_gemb, model.temporal_gproj)])  # (K*(card+2), d)
        self.depth_gesture_table = torch.cat([proj(emb.full_table()) for emb, proj in
                                              zip(model.depformer_gemb, model.depformer_gproj)])  # (S*(card+2), d)
        self.level_offsets = torch.arange(self.sizes.n_levels) * self.row_stride
        self.spk_temp_table = model.spk_tempemb.weight.detach().clone()
        self.spk_depth_table = torch.stack([e.weight.detach() for e in model.spk_depemb], dim=1)  # (n_spk, S, d)
        self.audio_stride = self.spec.audio_card + 1
        self.audio_offsets = torch.arange(self.spec.n_audio_codebooks) * self.audio_stride
        self.cond_tables = {}  # name -> (projected audio table (Q*(card+1), 2d) , text table (vocab+1, 2d), bias (2, 2d))
        audio = torch.cat([F.pad(t.weight.detach(), (0, 0, 0, 1)) for t in model.audio_procemb])  # zero row per book
        text = F.pad(model.text_procemb.weight.detach(), (0, 0, 0, 1))
        projs = (model.temp_condproj, model.dep_condproj)
        self.audio_table = torch.cat([F.linear(audio, p[0].weight) for p in projs], dim=1)  # (Q*(card+1), 2d)
        self.text_table = torch.cat([F.linear(text, p[1].weight) for p in projs], dim=1)  # (vocab+1, 2d)
        self.audio_bias = torch.cat([p[0].bias.detach() for p in projs])  # (2d,) temporal | depth
        self.text_bias = torch.cat([p[1].bias.detach() for p in projs])

    def _prepare_temporal(self, model: GestureLM) -> None:
        self.temporal = [self._temporal_layer(layer, model) for layer in model.temporal_transformer.layers]
        layers = model.temporal_transformer.layers
        self.memory_kv = {  # (L*2d, d): keys then values of every layer, for one memory vector
            name: self._cast(torch.cat([torch.cat([layer.cross_attns[i].key_projs[0].weight,
                                                   layer.cross_attns[i].val_projs[0].weight]) for layer in layers]))
            for i, name in enumerate(("audio", "text"))}
        self.out_norm = _norm_params(model.out_norm)
        self.classifier0 = self._cast(model.temporal_classifier.weight)
        self.depth_in = self._cast(torch.cat([lin.weight for lin in model.depformer_in]))  # (S*d, d)
        self.temporal_freqs = layers[0].rope.freqs

    def _temporal_layer(self, layer: TemporalLayer, model: GestureLM) -> _TemporalWeights:
        d = self.sizes.d_model
        sa, ca_a, ca_t = layer.self_attn, layer.cross_attns[0], layer.cross_attns[1]
        w_m, b_m = layer.memory_projs[0].weight, layer.memory_projs[0].bias
        mix = torch.cat([w_m[:, :d] @ ca_a.out_projs[0].weight, w_m[:, d:] @ ca_t.out_projs[0].weight], dim=1)
        null_audio = ca_a.val_projs[0](model.temp_condproj[0].bias)  # every key holds the same null value
        null_text = ca_t.val_projs[0](model.temp_condproj[1].bias)
        null_ca = layer.ca_gating(F.silu(F.linear(torch.cat([null_audio, null_text]), mix, b_m)))
        return _TemporalWeights(
            norm1=_norm_params(layer.norm1), norm2=_norm_params(layer.norm2),
            norm3=(_norm_params(layer.norm3[0]), _norm_params(layer.norm3[1])),
            qkv=self._cast(torch.cat([sa.in_projs[0].weight, sa.key_projs[0].weight, sa.val_projs[0].weight])),
            out=self._cast(sa.out_projs[0].weight),
            q_audio=self._cast(ca_a.in_projs[0].weight), q_text=self._cast(ca_t.in_projs[0].weight),
            mix=self._cast(mix), mix_bias=b_m.detach().clone(),
            ca_in=self._cast(layer.ca_gating.linear_in.weight), ca_out=self._cast(layer.ca_gating.linear_out.weight),
            ffn_in=self._cast(layer.gating.linear_in.weight), ffn_out=self._cast(layer.gating.linear_out.weight),
            null_ca=null_ca.detach())

    def _prepare_depth(self, model: GestureLM) -> None:
        masked = model.cross_masked
        self.open_positions = [s for s in range(self.sizes.n_depth) if not masked[s]]
        self.depth = [self._depth_layer(layer, model, masked) for layer in model.depth_transformer.layers]
        self.depth_fold = self._cast(torch.cat([self._depth_fold(layer) for layer in model.depth_transformer.layers]))
        self.classifiers = [self._cast(c.weight) for c in model.depformer_classifier]

    def _depth_fold(self, layer: DepthLayer) -> torch.Tensor:
        """(len(open)*d, 2d): pre-activation of the cross-attention block per open position from [m_audio, m_text]."""
        d = self.sizes.d_model
        w_m = layer.memory_projs[0].weight
        ca_a, ca_t = layer.cross_attns
        return torch.cat([torch.cat([w_m[:, :d] @ ca_a.out_projs[s].weight @ ca_a.val_projs[0].weight,
                                     w_m[:, d:] @ ca_t.out_projs[s].weight @ ca_t.val_projs[0].weight], dim=1)
                          for s in self.open_positions])

    def _depth_layer(self, layer: DepthLayer, model: GestureLM, masked: torch.Tensor) -> _DepthWeights:
        sa, ca_a, ca_t = layer.self_attn, layer.cross_attns[0], layer.cross_attns[1]
        w_m, b_m = layer.memory_projs[0].weight, layer.memory_projs[0].bias
        d = self.sizes.d_model
        null_audio = ca_a.val_projs[0](model.dep_condproj[0].bias)
        null_text = ca_t.val_projs[0](model.dep_condproj[1].bias)
        const = []
        for s in range(self.sizes.n_depth):
            pre = b_m if masked[s] else b_m + w_m[:, :d] @ ca_a.out_projs[s](null_audio) + w_m[:, d:] @ ca_t.out_projs[s](null_text)
            const.append(layer.ca_gating[s](F.silu(pre)))
        return _DepthWeights(
            norm1=_norm_params(layer.norm1), norm2=_norm_params(layer.norm2),
            qkv=[self._cast(torch.cat([_rotate_rows(sa.in_projs[s].weight, s, layer.rope.freqs, layer.heads),
                                       _rotate_rows(sa.key_projs[s].weight, s, layer.rope.freqs, layer.heads),
                                       sa.val_projs[s].weight])) for s in range(self.sizes.n_depth)],
            out=[self._cast(w.weight) for w in sa.out_projs],
            ffn_in=[self._cast(g.linear_in.weight) for g in layer.gating],
            ffn_out=[self._cast(g.linear_out.weight) for g in layer.gating],
            ca_in=[self._cast(g.linear_in.weight) for g in layer.ca_gating],
            ca_out=[self._cast(g.linear_out.weight) for g in layer.ca_gating],
            const_ca=torch.stack(const).detach(), mix_bias=b_m.detach().clone())

    def _new_state(self) -> LMStepState:
        s = self.sizes
        heads_t, heads_d = s.temporal_heads, s.depth_heads
        return LMStepState(
            batch_size=self.batch,
            self_caches=[RingKVCache(self.batch, heads_t, s.d_model // heads_t, s.self_context_steps)
                         for _ in range(s.temporal_layers)],
            audio_caches=[RingKVCache(1, heads_t, s.d_model // heads_t, s.cross_context_steps)
                          for _ in range(s.temporal_layers)],
            text_caches=[RingKVCache(1, heads_t, s.d_model // heads_t, s.cross_context_steps)
                         for _ in range(s.temporal_layers)],
            depth_keys=torch.zeros(s.depth_layers, self.batch, heads_d, s.n_depth, s.d_model // heads_d),
            depth_values=torch.zeros(s.depth_layers, self.batch, heads_d, s.n_depth, s.d_model // heads_d),
            depth_z=torch.zeros(self.batch, s.n_depth, s.d_model),
            depth_ca=torch.zeros(s.depth_layers, s.n_depth, s.d_model))

    # ----- session --------------------------------------------------------------------------------------------
    def set_speaker(self, speaker: int) -> None:
        if not 0 <= speaker < self.sizes.n_speakers:
            raise ValueError(f"speaker: must be in [0, {self.sizes.n_speakers - 1}], got {speaker}")
        self.spk_temp = self.spk_temp_table[speaker]  # (d,)
        self.spk_depth = self.spk_depth_table[speaker]  # (S, d)

    def reset(self) -> None:
        self.state.reset()

    # ----- one step -------------------------------------------------------------------------------------------
    def condition_memories(self, text: int, audio: torch.Tensor) -> torch.Tensor:
        """Row-0 projected memories (2, 2d): [audio | text] x [temporal d | depth d]; −1 gives the bias alone."""
        text_row = self.text_table[text if text >= 0 else self.spec.text_vocab] + self.text_bias
        codes = torch.where(audio < 0, self.spec.audio_card, audio) + self.audio_offsets
        audio_row = self.audio_table.index_select(0, codes).sum(0) + self.audio_bias
        return torch.stack([audio_row, text_row])

    def begin_step(self, history: torch.Tensor, text: int, audio: torch.Tensor) -> torch.Tensor:
        """history (K,) tokens of the previous step (−1 at the start); text: token id or −1; audio (Q,) codes or −1.
        Runs the temporal transformer; returns level-0 logits (B, card+1)."""
        d, st = self.sizes.d_model, self.state
        memories = self.condition_memories(text, audio)  # (2, 2d)
        index = table_index(history, self.sizes.card) + self.level_offsets
        x = self.gesture_table.index_select(0, index).sum(0) + self.spk_temp  # (d,)
        x = x.expand(self.batch, d).clone()  # (B, d)
        h = self._temporal(x, memories[:, :d], st.step)  # (B, d) before out_norm
        self.temporal_out = h
        normed = _norm(h, self.out_norm)
        st.depth_z.copy_(linear(normed, self.depth_in).view(self.batch, -1, d) + self.spk_depth)  # (B, S, d)
        self._depth_cross(memories[:, d:])
        st.step += 1
        return linear(normed, self.classifier0)

    def _temporal(self, x: torch.Tensor, memories: torch.Tensor, t: int) -> torch.Tensor:
        s, st = self.sizes, self.state
        heads = s.temporal_heads
        angles = t * self.temporal_freqs  # (Dh/2,) float32, as gesture.nn.rope computes them
        rope = (angles.cos(), angles.sin())
        position = torch.tensor([t])
        masks: dict = {}
        kv = {name: linear(memories[i:i + 1], self.memory_kv[name]).view(s.temporal_layers, 2, heads, 1, -1)
              for i, name in enumerate(("audio", "text"))}  # (L, 2, H, 1, Dh)
        for i, w in enumerate(self.temporal):
            qkv = linear(_norm(x, w.norm1), w.qkv).view(self.batch, 3, heads, 1, -1)  # (B, 3, H, 1, Dh)
            q, k = _rotate(qkv[:, 0], *rope), _rotate(qkv[:, 1], *rope)
            keys, values, k_pos = st.self_caches[i].append(k, qkv[:, 2])
            if "self" not in masks:  # every layer's ring holds the same positions
                masks["self"] = attention_mask(position, k_pos, s.self_context_steps)
            x = x + linear(_attend(q, keys, values, masks["self"]), w.out)
            audio_query = _norm(x[:1], w.norm3[0])
            text_query = _norm(audio_query, w.norm3[1])
            audio = self._cross(st.audio_caches[i], linear(audio_query, w.q_audio), kv["audio"][i], rope, masks)
            text = self._cross(st.text_caches[i], linear(text_query, w.q_text), kv["text"][i], rope, masks)
            mixed = F.silu(linear(torch.cat([audio, text], dim=-1), w.mix) + w.mix_bias)  # (1, d)
            ca = _ffn(mixed, w.ca_in, w.ca_out)
            x = x + (torch.cat([ca, w.null_ca[None]]) if self.batch == 2 else ca)
            x = x + _ffn(_norm(x, w.norm2), w.ffn_in, w.ffn_out)
        return x

    def _cross(self, cache: RingKVCache, q: torch.Tensor, kv: torch.Tensor, rope: tuple, masks: dict) -> torch.Tensor:
        heads = self.sizes.temporal_heads
        q = _rotate(q.view(1, heads, 1, -1), *rope)  # (1, H, 1, Dh)
        keys, values, k_pos = cache.append(_rotate(kv[0][None], *rope), kv[1][None])
        if "cross" not in masks:  # every layer's audio and text rings hold the same positions
            masks["cross"] = attention_mask(k_pos.new_tensor([cache.next_position - 1]), k_pos,
                                            self.sizes.cross_context_steps)
        return _attend(q, keys, values, masks["cross"])

    def _depth_cross(self, memories: torch.Tensor) -> None:
        """Row-0 cross-attention block outputs of every depth layer and position (others are constants)."""
        st, d = self.state, self.sizes.d_model
        n_open = len(self.open_positions)
        pre = linear(memories.reshape(1, 2 * d), self.depth_fold).view(len(self.depth), n_open, d)
        for i, w in enumerate(self.depth):
            st.depth_ca[i].copy_(w.const_ca)
            for j, s in enumerate(self.open_positions):
                st.depth_ca[i, s] = _ffn(F.silu(pre[i, j] + w.mix_bias), w.ca_in[s], w.ca_out[s])

    def depth_logits(self, k: int, token: int) -> torch.Tensor:
        """Depth position k with level-k token `token` (shared by all rows) -> logits (B, card+1) of level k+1."""
        st = self.state
        heads = self.sizes.depth_heads
        row = self.depth_gesture_table[k * self.row_stride + (token if token >= 0 else self.row_stride - 1)]
        z = st.depth_z[:, k] + row  # (B, d)
        for i, w in enumerate(self.depth):
            qkv = linear(_norm(z, w.norm1), w.qkv[k]).view(self.batch, 3, heads, 1, -1)  # (B, 3, H, 1, Dh), RoPE'd
            q = qkv[:, 0]
            st.depth_keys[i, :, :, k] = qkv[:, 1, :, 0]
            st.depth_values[i, :, :, k] = qkv[:, 2, :, 0]
            keys, values = st.depth_keys[i, :, :, :k + 1], st.depth_values[i, :, :, :k + 1]  # (B, H, k+1, Dh)
            weights = torch.softmax((q @ keys.transpose(-1, -2)) * q.shape[-1] ** -0.5, dim=-1)
            z = z + linear((weights @ values).flatten(1), w.out[k])
            ca = st.depth_ca[i, k]
            z = z + (torch.stack([ca, w.const_ca[k]]) if self.batch == 2 else ca)
            z = z + _ffn(_norm(z, w.norm2), w.ffn_in[k], w.ffn_out[k])
        return linear(z, self.classifiers[k])

    def va_logit(self, face_logits: torch.Tensor | None = None) -> float:
        """Voice-activity logit of row 0 for the current step; face_logits (n_face, card+1) if the head uses them."""
        model = self._va_model
        features = self.temporal_out[:1]
        if model.sizes.va_use_face_logits:
            features = torch.cat([features, model.vad_face_proj(face_logits.reshape(1, -1))], dim=-1)
        return float(model.vad_predictor(features)[0, 0])
