"""Training schedules of the gesture LM (docs/reference_facts.md §3), as functions of the (fractional) epoch.

- before `warmup_epochs`: unconditional (every condition token dropped);
- then each sample's audio and text are dropped independently with a probability going 1.0 → `cond_drop_final`
  linearly until `cond_drop_end_epoch` (classifier-free guidance training);
- from `pad_start_epoch`, the lower and face *input* tokens of a growing share of samples become pad, reaching
  `pad_rate` at `pad_full_epoch`;
- the Gumbel-softmax temperature goes `tau_start` → `tau_end` over `tau_epochs` after the warm-up.
"""

from __future__ import annotations

import torch

from gesture.lm.config import LMConfig, LMTrainConfig


def _ramp(epoch: float, start: float, end: float, v0: float, v1: float) -> float:
    if epoch <= start:
        return v0
    if epoch >= end:
        return v1
    return v0 + (v1 - v0) * (epoch - start) / (end - start)


def condition_drop_probability(epoch: float, cfg: LMTrainConfig) -> float:
    if epoch < cfg.warmup_epochs:
        return 1.0
    return _ramp(epoch, cfg.warmup_epochs, cfg.cond_drop_end_epoch, 1.0, cfg.cond_drop_final)


def pad_input_rate(epoch: float, cfg: LMTrainConfig) -> float:
    if epoch < cfg.pad_start_epoch:
        return 0.0
    return _ramp(epoch, cfg.pad_start_epoch, cfg.pad_full_epoch, 0.0, cfg.pad_rate)


def gumbel_tau(epoch: float, cfg: LMTrainConfig) -> float:
    return _ramp(epoch, cfg.warmup_epochs, cfg.warmup_epochs + cfg.tau_epochs, cfg.tau_start, cfg.tau_end)


def drop_conditions(
    text: torch.Tensor, audio: torch.Tensor, probability: float, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """text (B, T), audio (B, Q, T): per sample, set text and (independently) audio to −1 with `probability`."""
    batch = text.shape[0]
    drop_text = torch.rand(batch, generator=generator) < probability
    drop_audio = torch.rand(batch, generator=generator) < probability
    text = torch.where(drop_text[:, None], torch.full_like(text, -1), text)
    audio = torch.where(drop_audio[:, None, None], torch.full_like(audio, -1), audio)
    return text, audio


def pad_inputs(
    tokens: torch.Tensor, sizes: LMConfig, rate: float, generator: torch.Generator | None = None
) -> torch.Tensor:
    """tokens (B, K, T): for a `rate` share of samples, lower and face levels become pad (a new tensor)."""
    chosen = torch.rand(tokens.shape[0], generator=generator) < rate  # (B,)
    levels = torch.zeros(tokens.shape[1], dtype=torch.bool)
    levels[sizes.n_upper :] = True  # lower then face
    mask = chosen[:, None, None] & levels[None, :, None]  # (B, K, 1)
    return torch.where(mask, torch.full_like(tokens, sizes.pad_token), tokens)
