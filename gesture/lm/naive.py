"""A cache-free step engine with the `LMStepper` contract: every step recomputes the temporal transformer over its
whole receptive field, and every depth level recomputes all depth positions. It is a test oracle (and the
benchmark's baseline), never the runtime's path; its outputs equal the cached path because the window covers the
full receptive field (L * (self_context − 1) + cross_context steps)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import torch

from gesture.lm.model import GestureLM
from gesture.lm.sampling import guided_row
from gesture.nn.streaming import StreamingModule, StreamingState


@dataclass
class NaiveState(StreamingState):
    window: int = 1
    history: deque = field(default_factory=deque)  # (history (K,), text (), audio (Q,)) per step, at most `window`
    step: int = 0

    def __post_init__(self) -> None:
        self.history = deque(maxlen=self.window)

    def reset(self) -> None:
        self.history.clear()
        self.step = 0


class NaiveStepper(StreamingModule[NaiveState]):
    def __init__(self, model: GestureLM, guided: bool) -> None:
        super().__init__()
        self.model, self.sizes = model, model.sizes
        self.batch = 2 if guided else 1
        self.has_va = model.sizes.va_head
        self.needs_face_logits = self.has_va and model.sizes.va_use_face_logits
        s = self.sizes
        self.window = s.temporal_layers * (s.self_context_steps - 1) + s.cross_context_steps
        self.speaker = torch.tensor([0])

    def _init_streaming_state(self, batch_size: int) -> NaiveState:
        if batch_size != self.batch:
            raise ValueError(f"this step path runs {self.batch} rows, not {batch_size}")
        return NaiveState(batch_size, self.window)

    def set_speaker(self, speaker: int) -> None:
        self.speaker = torch.tensor([speaker])

    def _rows(self, x: torch.Tensor) -> torch.Tensor:
        """(1, ...) conditioned tensor -> (B, ...) with the null row all −1."""
        return x if self.batch == 1 else torch.cat([x, torch.full_like(x, -1)])

    def begin_step(
        self, history: torch.Tensor, text: int, audio: torch.Tensor, guidance: float | None = None
    ) -> torch.Tensor:
        state = self._streaming_state
        state.history.append((history.clone(), torch.tensor(text), audio.clone()))
        hist = torch.stack([h for h, _, _ in state.history], dim=-1)[None].expand(self.batch, -1, -1)  # (B, K, W)
        text_w = self._rows(torch.stack([t for _, t, _ in state.history])[None])  # (B, W)
        audio_w = self._rows(torch.stack([a for _, _, a in state.history], dim=-1)[None])  # (B, Q, W)
        model, speaker = self.model, self.speaker.expand(self.batch)
        audio_sum, text_emb = model.condition_embeddings(text_w, audio_w)
        offset = state.step - len(state.history) + 1
        temporal = model.temporal_forward(hist, audio_sum, text_emb, speaker, offset)[:, -1:]  # (B, 1, d)
        self.temporal_out = temporal[:, 0]
        self.normed = model.out_norm(temporal)
        self.current_cond = (audio_sum[:, -1:], text_emb[:, -1:])
        self.current = torch.zeros(self.batch, self.sizes.n_levels, 1, dtype=torch.long)  # (B, K, 1)
        state.step += 1
        return self._rows_or_guided(model.temporal_classifier(self.normed[:, 0]), guidance)

    def depth_logits(self, k: int, token: int, guidance: float | None = None) -> torch.Tensor:
        self.current[:, k] = token
        logits = self.model.depth_forward(
            self.normed, self.current, *self.current_cond, self.speaker.expand(self.batch)
        )
        return self._rows_or_guided(logits[:, 0, k], guidance)  # (B, V) or (V,)

    @staticmethod
    def _rows_or_guided(rows: torch.Tensor, guidance: float | None) -> torch.Tensor:
        return rows if guidance is None else guided_row(rows, guidance)

    def va_logit(self, face_logits: torch.Tensor | None = None) -> float:
        features = self.temporal_out[:1]
        if self.sizes.va_use_face_logits:
            features = torch.cat([features, self.model.vad_face_proj(face_logits.reshape(1, -1))], dim=-1)
        return float(self.model.vad_predictor(features)[0, 0])
