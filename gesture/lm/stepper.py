"""The cached, step-by-step form of `GestureLM` for streaming generation on CPU.

`LMStepper(model, guided, dtype)` copies the model's weights once into fused, precomputed forms
(`gesture.lm.step_weights`), then runs one 80 ms step as `begin_step(history, text, audio)` (temporal transformer,
level-0 logits) followed by `depth_logits(k, token_k)` for k = 0..K-2 (the depth transformer, one level at a
time). Row 0 of every batch is the conditioned stream; with `guided` a row 1 runs the same history with the empty
condition (CFG's null half). Both calls return the logits of every row, (B, card+1), or with `guidance=c` the
guided logits null + c·(cond − null) as one (card+1,) row: the classifiers are linear, so that is the classifier
of the guided hidden state, one row instead of two and no guidance ops on the logits.

Weights of the matrix products are stored in `dtype` (a `gesture.nn.weights` form: float32, bfloat16, or per-row
int8 with bfloat16 activations, each with the fastest kernel this CPU runs). The residual streams, norms, softmax and
the temporal caches stay float32; the depth keys/values are stored in the products' output dtype (they are its
outputs, unrounded). Every buffer is allocated once: the rings (`gesture.nn.RingKVCache.push`) hold exactly the
attention windows (self 25, cross 50 steps), so a query sees every filled slot and needs no mask. Nothing grows with
the session.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gesture.lm.embeddings import table_index
from gesture.lm.layers import LAYER_NORM_EPS
from gesture.lm.model import GestureLM
from gesture.lm.step_weights import depth_fold, depth_weights, memory_kv, norm_params, temporal_weights
from gesture.nn.kv_cache import RingKVCache
from gesture.nn.rope import rope_tables, rotate_with_tables
from gesture.nn.streaming import StreamingModule, StreamingState
from gesture.nn.weights import StepWeight, check_form, gated_ffn, step_weight

F32 = torch.float32
attend = F.scaled_dot_product_attention


def _norm(x: torch.Tensor, params: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    return F.layer_norm(x, (x.shape[-1],), params[0], params[1], LAYER_NORM_EPS)


@dataclass
class LMStepState(StreamingState):
    """Per-session state: the temporal rings and the depth scratch of the current step."""

    self_rings: list[RingKVCache]  # per temporal layer, (B, H, self_context, Dh), keys RoPE'd
    cross_rings: list[RingKVCache]  # per temporal layer, (2, H, cross_context, Dh): audio, text memories of row 0
    temporal_ca: torch.Tensor  # (L, B, d): row 0 written per step, row 1 the null constant
    depth_kv: torch.Tensor  # (L_depth, B, S, 2d) keys | values, in the products' dtype
    depth_z: torch.Tensor  # (B, S, d) depth inputs without the token embedding
    depth_ca: torch.Tensor  # (L_depth, S, B, d) cross-attention block outputs; constants except open row 0
    step: int = 0

    def reset(self) -> None:
        for ring in self.self_rings + self.cross_rings:
            ring.reset()
        self.step = 0


class LMStepper(StreamingModule[LMStepState]):
    """Cached step path of a `GestureLM`; see the module docstring. Like every streaming module it runs between
    `start_streaming(batch)` (or `with stepper.streaming(batch):`) and `stop_streaming()`, and
    `reset_streaming()` starts a new session; its batch is `stepper.batch` (2 rows when guided, else 1)."""

    def __init__(self, model: GestureLM, guided: bool, dtype: str = "float32") -> None:
        super().__init__()
        self.sizes, self.spec = model.sizes, model.spec
        self.batch = 2 if guided else 1
        self.dtype = check_form(dtype)
        self.has_va = model.sizes.va_head
        self.needs_face_logits = self.has_va and model.sizes.va_use_face_logits
        self.vad_predictor = model.vad_predictor if self.has_va else None  # small heads: submodules, not copies
        self.vad_face_proj = model.vad_face_proj if self.needs_face_logits else None
        with torch.no_grad():
            self._prepare_tables(model)
            self._prepare_temporal(model)
            self._prepare_depth(model)
        self.set_speaker(0)

    # ----- preparation ----------------------------------------------------------------------------------------
    def _cast(self, w: torch.Tensor) -> StepWeight:
        return step_weight(w, self.dtype, self.batch)

    def _prepare_tables(self, model: GestureLM) -> None:
        card = self.sizes.card
        self.row_stride = card + 2  # codes, pad, zero row
        self.gesture_table = torch.cat(
            [proj(emb.full_table()) for emb, proj in zip(model.temporal_gemb, model.temporal_gproj)]
        )  # (K*(card+2), d)
        self.depth_gesture_table = torch.cat(
            [proj(emb.full_table()) for emb, proj in zip(model.depformer_gemb, model.depformer_gproj)]
        )  # (S*(card+2), d)
        self.level_offsets = torch.arange(self.sizes.n_levels) * self.row_stride
        self.spk_temp_table = model.spk_tempemb.weight.detach().clone()
        self.spk_depth_table = torch.stack([e.weight.detach() for e in model.spk_depemb], dim=1)  # (n_spk, S, d)
        self.audio_stride = self.spec.audio_card + 1
        self.audio_offsets = torch.arange(self.spec.n_audio_codebooks) * self.audio_stride
        audio = torch.cat([F.pad(t.weight.detach(), (0, 0, 0, 1)) for t in model.audio_procemb])  # zero row per book
        text = F.pad(model.text_procemb.weight.detach(), (0, 0, 0, 1))
        projs = (model.temp_condproj, model.dep_condproj)
        self.audio_table = torch.cat([F.linear(audio, p[0].weight) for p in projs], dim=1)  # (Q*(card+1), 2d)
        self.text_table = torch.cat([F.linear(text, p[1].weight) for p in projs], dim=1)  # (vocab+1, 2d)
        self.audio_bias = torch.cat([p[0].bias.detach() for p in projs])  # (2d,) temporal | depth
        self.text_bias = torch.cat([p[1].bias.detach() for p in projs])

    def _prepare_temporal(self, model: GestureLM) -> None:
        layers = model.temporal_transformer.layers
        self.temporal = [temporal_weights(layer, model, self._cast) for layer in layers]
        self.memory_kv = memory_kv(model, self._cast)
        self.out_norm = norm_params(model.out_norm)
        self.classifier0 = self._cast(model.temporal_classifier.weight)
        self.depth_in = self._cast(torch.cat([lin.weight for lin in model.depformer_in]))  # (S*d, d)
        self.temporal_freqs = layers[0].rope.freqs

    def _prepare_depth(self, model: GestureLM) -> None:
        masked = model.cross_masked
        layers = model.depth_transformer.layers
        self.open_positions = [s for s in range(self.sizes.n_depth) if not masked[s]]
        self.depth = [depth_weights(layer, model, self._cast) for layer in layers]
        self.depth_fold = self._cast(
            torch.cat([depth_fold(layer, self.open_positions, self.sizes.d_model) for layer in layers])
        )
        biases = [layer.memory_projs[0].bias.detach() for layer in layers]
        self.depth_mix_bias = torch.stack(biases)[:, None]  # (L, 1, d)
        self.classifiers = [self._cast(c.weight) for c in model.depformer_classifier]

    def _init_streaming_state(self, batch_size: int) -> LMStepState:
        if batch_size != self.batch:
            raise ValueError(
                f"this step path runs {self.batch} rows ({'guided' if self.batch == 2 else 'unguided'}), "
                f"not {batch_size}"
            )
        s, b, d = self.sizes, self.batch, self.sizes.d_model
        heads, head_dim = s.temporal_heads, d // s.temporal_heads
        depth_dtype = self.depth[0].qkv[0].out_dtype if self.depth else F32
        temporal_ca = torch.zeros(s.temporal_layers, b, d)
        depth_ca = torch.zeros(s.depth_layers, s.n_depth, b, d)
        for i, w in enumerate(self.temporal):
            temporal_ca[i, 1:] = w.null_ca
        for i, w in enumerate(self.depth):
            depth_ca[i] = w.const_ca[:, None]
        state = LMStepState(
            batch_size=b,
            self_rings=[RingKVCache(b, heads, head_dim, s.self_context_steps) for _ in range(s.temporal_layers)],
            cross_rings=[RingKVCache(2, heads, head_dim, s.cross_context_steps) for _ in range(s.temporal_layers)],
            temporal_ca=temporal_ca,
            depth_kv=torch.zeros(s.depth_layers, b, s.n_depth, 2 * d, dtype=depth_dtype),
            depth_z=torch.zeros(b, s.n_depth, d),
            depth_ca=depth_ca,
        )
        self._make_views(state)
        return state

    def _make_views(self, st: LMStepState) -> None:
        """Views into the state used every step, made once (the state is only ever written in place)."""
        s, d = self.sizes, self.sizes.d_model
        heads = s.depth_heads

        def prefix(i: int, k: int, half: slice) -> torch.Tensor:  # (B, H, k+1, Dh)
            return st.depth_kv[i, :, : k + 1, half].unflatten(-1, (heads, -1)).transpose(1, 2)

        self._kv_slots = [[st.depth_kv[i, :, k] for k in range(s.n_depth)] for i in range(s.depth_layers)]
        self._keys = [[prefix(i, k, slice(0, d)) for k in range(s.n_depth)] for i in range(s.depth_layers)]
        self._values = [[prefix(i, k, slice(d, 2 * d)) for k in range(s.n_depth)] for i in range(s.depth_layers)]
        self._ca_rows = [[st.depth_ca[i, k] for k in range(s.n_depth)] for i in range(s.depth_layers)]
        self._open_ca_rows = [st.depth_ca[i, k, :1] for i in range(s.depth_layers) for k in self.open_positions]
        self._depth_z_rows = [st.depth_z[:, k] for k in range(s.n_depth)]

    # ----- session --------------------------------------------------------------------------------------------
    def set_speaker(self, speaker: int) -> None:
        if not 0 <= speaker < self.sizes.n_speakers:
            raise ValueError(f"speaker: must be in [0, {self.sizes.n_speakers - 1}], got {speaker}")
        self.spk_temp = self.spk_temp_table[speaker]  # (d,)
        self.spk_depth = self.spk_depth_table[speaker]  # (S, d)

    @property
    def state(self) -> LMStepState:
        if self._streaming_state is None:
            raise RuntimeError("LMStepper is not streaming; call start_streaming(stepper.batch) first")
        return self._streaming_state

    # ----- one step -------------------------------------------------------------------------------------------
    def condition_memories(self, text: int, audio: torch.Tensor) -> torch.Tensor:
        """Row-0 projected memories (2, 2d): [audio | text] x [temporal d | depth d]; −1 gives the bias alone."""
        text_row = self.text_table[text if text >= 0 else self.spec.text_vocab] + self.text_bias
        codes = torch.where(audio < 0, self.spec.audio_card, audio) + self.audio_offsets
        audio_row = self.audio_table.index_select(0, codes).sum(0) + self.audio_bias
        return torch.stack([audio_row, text_row])

    def begin_step(
        self, history: torch.Tensor, text: int, audio: torch.Tensor, guidance: float | None = None
    ) -> torch.Tensor:
        """history (K,) tokens of the previous step (−1 at the start); text: token id or −1; audio (Q,) codes or −1.
        Runs the temporal transformer; returns level-0 logits (B, card+1), or (card+1,) guided by `guidance`."""
        d, st = self.sizes.d_model, self.state
        memories = self.condition_memories(text, audio)  # (2, 2d)
        index = table_index(history, self.sizes.card) + self.level_offsets
        x = self.gesture_table.index_select(0, index).sum(0) + self.spk_temp  # (d,)
        h = self._temporal(x.expand(self.batch, d), memories[:, :d])  # (B, d) before out_norm
        self.temporal_out = h
        normed = _norm(h, self.out_norm)
        st.depth_z.copy_(self.depth_in.apply(normed).view(self.batch, -1, d) + self.spk_depth)  # (B, S, d)
        self._depth_cross(memories[:, d:])
        st.step += 1
        return self._logits(normed, self.classifier0, guidance)

    def _temporal(self, x: torch.Tensor, memories: torch.Tensor) -> torch.Tensor:
        """x (B, d) input of step t, memories (2, d) [audio, text] -> (B, d); appends to the rings."""
        s, st, t = self.sizes, self.state, self.state.step
        heads, d = s.temporal_heads, s.d_model
        rope = rope_tables(torch.tensor(t), self.temporal_freqs)  # (Dh,) cos, sin at position t
        memory_kv = self._append_memories(memories, rope)
        for i, w in enumerate(self.temporal):
            qkv = w.qkv.apply(_norm(x, w.norm1)).float().view(self.batch, 3, heads, 1, -1)  # (B, 3, H, 1, Dh)
            qk = rotate_with_tables(qkv[:, :2], *rope)  # (B, 2, H, 1, Dh)
            keys, values = st.self_rings[i].push(qk[:, 1, :, 0], qkv[:, 2, :, 0])  # (B, H, n, Dh)
            attended = attend(qk[:, 0], keys, values)  # (B, H, 1, Dh)
            x = x + w.out.apply(attended.reshape(self.batch, d))
            audio_query = _norm(x[:1], w.norm3[0])
            queries = w.cross_q.apply(torch.cat([audio_query, _norm(audio_query, w.norm3[1])])).float()  # (2, 2d)
            q = rotate_with_tables(torch.stack([queries[0, :d], queries[1, d:]]).view(2, heads, 1, -1), *rope)
            crossed = attend(q, *memory_kv[i])  # (2, H, 1, Dh)
            mixed = F.silu(w.mix.apply(crossed.reshape(1, 2 * d)) + w.mix_bias)  # (1, d) float32
            st.temporal_ca[i, :1].copy_(gated_ffn(mixed, w.ca_in, w.ca_out))
            x = x + st.temporal_ca[i]
            x = x + gated_ffn(_norm(x, w.norm2), w.ffn_in, w.ffn_out)
        return x

    def _append_memories(self, memories: torch.Tensor, rope: tuple) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Keys and values of this step's audio and text memories into every layer's ring; returns each layer's
        filled keys and values, (2, H, n, Dh) each."""
        s, st = self.sizes, self.state
        rows = s.temporal_layers * 2 * s.d_model
        kv = self.memory_kv.apply(memories).float()  # (2, 2 * rows): each memory times both weight halves
        kv = torch.stack([kv[0, :rows], kv[1, rows:]]).view(2, s.temporal_layers, 2, s.temporal_heads, -1)
        keys = rotate_with_tables(kv[:, :, 0], *rope).transpose(0, 1)  # (L, 2, H, Dh)
        values = kv[:, :, 1].transpose(0, 1)
        return [ring.push(k, v) for ring, k, v in zip(st.cross_rings, keys, values)]

    def _depth_cross(self, memories: torch.Tensor) -> None:
        """Row-0 cross-attention block outputs of every depth layer and open position (the rest are constants)."""
        d, n_open = self.sizes.d_model, len(self.open_positions)
        pre = self.depth_fold.apply(memories.reshape(1, 2 * d)).view(len(self.depth), n_open, d)
        mixed = F.silu(pre + self.depth_mix_bias).view(-1, 1, d).unbind(0)  # (L * n_open) x (1, d)
        for j, (x, out) in enumerate(zip(mixed, self._open_ca_rows)):
            w, s = self.depth[j // n_open], self.open_positions[j % n_open]
            out.copy_(gated_ffn(x, w.ca_in[s], w.ca_out[s]))

    def depth_logits(self, k: int, token: int, guidance: float | None = None) -> torch.Tensor:
        """Depth position k with level-k token `token` (shared by all rows) -> logits of level k+1: (B, card+1),
        or (card+1,) guided by `guidance`."""
        heads, d, b = self.sizes.depth_heads, self.sizes.d_model, self.batch
        row = self.depth_gesture_table[k * self.row_stride + (token if token >= 0 else self.row_stride - 1)]
        z = self._depth_z_rows[k] + row  # (B, d)
        for i, w in enumerate(self.depth):
            qkv = w.qkv[k].apply(_norm(z, w.norm1))  # (B, 3d), RoPE'd by the weights
            self._kv_slots[i][k].copy_(qkv[:, d:])
            attended = attend(qkv[:, :d].view(b, heads, 1, -1), self._keys[i][k], self._values[i][k])  # (B, H, 1, Dh)
            z = z + w.out[k].apply(attended.reshape(b, d))
            z = z + self._ca_rows[i][k]
            z = z + gated_ffn(_norm(z, w.norm2), w.ffn_in[k], w.ffn_out[k])
        return self._logits(z, self.classifiers[k], guidance)

    def _logits(self, h: torch.Tensor, classifier: StepWeight, guidance: float | None) -> torch.Tensor:
        """Classifier logits (B, V) of the rows h (B, d), or (V,) of the guided row lerp(null, cond, guidance)."""
        if guidance is None:
            return classifier.apply(h).float()
        if self.batch == 1 or guidance == 1.0:
            return classifier.apply(h[:1]).float()[0]
        return classifier.apply(torch.lerp(h[1:], h[:1], guidance)).float()[0]

    def va_logit(self, face_logits: torch.Tensor | None = None) -> float:
        """Voice-activity logit of row 0 for the current step; face_logits (n_face, card+1) if the head uses them."""
        features = self.temporal_out[:1]
        if self.needs_face_logits:
            features = torch.cat([features, self.vad_face_proj(face_logits.reshape(1, -1))], dim=-1)
        return float(self.vad_predictor(features)[0, 0])
