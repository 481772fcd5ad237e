"""Training losses of the gesture LM (docs/reference_facts.md §3): weighted per-level CE, InfoNCE on Gumbel-softmax
latents, and the voice-activity BCE."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def level_weights(n_levels: int, face_levels: range, face_weight: float) -> torch.Tensor:
    """(K,) CE weights: 1/K per level, face levels additionally × face_weight."""
    weights = torch.full((n_levels,), 1.0 / n_levels)
    weights[list(face_levels)] *= face_weight
    return weights


def token_ce(logits: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor, pad_token: int) -> torch.Tensor:
    """logits (B, T, K, V), targets (B, K, T) -> Σ_k w_k · mean CE of level k over its non-pad targets."""
    targets = targets.transpose(1, 2)  # (B, T, K)
    per_token = F.cross_entropy(logits.flatten(0, 2), targets.flatten().clamp_min(0), reduction="none")
    per_token = per_token.view_as(targets)
    valid = ((targets != pad_token) & (targets >= 0)).to(per_token.dtype)
    per_level = (per_token * valid).sum((0, 1)) / valid.sum((0, 1)).clamp_min(1.0)  # (K,)
    return (per_level * weights.to(per_level.device)).sum()


def summed_latents(one_hot: torch.Tensor, codebooks: list[torch.Tensor]) -> torch.Tensor:
    """one_hot (B, T, k, card) for the k levels of one codec, codebooks k × (card, D) -> (B, T, D)."""
    return sum(one_hot[:, :, i] @ book for i, book in enumerate(codebooks))


def segment_info_nce(
    target: torch.Tensor, predicted: torch.Tensor, segment_steps: int, temperature: float
) -> torch.Tensor:
    """target, predicted (B, T, D): mean-pool segments of `segment_steps`, L2-normalise, InfoNCE in the
    target → prediction direction with diagonal positives. Trailing steps that fill no segment are dropped."""
    segments = target.shape[1] // segment_steps
    if segments == 0:
        raise ValueError(f"InfoNCE needs at least {segment_steps} steps per window, got {target.shape[1]}")

    def pooled(x: torch.Tensor) -> torch.Tensor:
        x = x[:, : segments * segment_steps].unflatten(1, (segments, segment_steps)).mean(2)  # (B, n, D)
        return F.normalize(x.flatten(0, 1), dim=-1)  # (B*n, D)

    anchors, candidates = pooled(target), pooled(predicted)
    similarity = anchors @ candidates.T / temperature  # (B*n, B*n)
    return F.cross_entropy(similarity, torch.arange(len(similarity), device=similarity.device))


def contrastive_loss(
    logits: torch.Tensor,
    targets: torch.Tensor,
    codebooks: list[torch.Tensor],
    level_groups: list[slice],
    tau: float,
    segment_steps: int,
    temperature: float,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Hard Gumbel-softmax samples of the code logits (pad excluded) are turned into each codec's summed latent
    and compared with the ground truth's by segment InfoNCE; the mean over codecs."""
    card = codebooks[0].shape[0]
    code_logits = logits[..., :card]  # (B, T, K, card)
    gumbel = -torch.empty_like(code_logits).exponential_(generator=generator).log()
    soft = torch.softmax((code_logits + gumbel) / tau, dim=-1)
    hard = F.one_hot(soft.argmax(-1), card).to(soft.dtype)
    samples = hard + soft - soft.detach()  # straight-through
    truth = F.one_hot(targets.transpose(1, 2).clamp(0, card - 1), card).to(soft.dtype)  # (B, T, K, card)
    losses = [
        segment_info_nce(
            summed_latents(truth[:, :, g], codebooks[g]),
            summed_latents(samples[:, :, g], codebooks[g]),
            segment_steps,
            temperature,
        )
        for g in level_groups
        if g.stop > g.start
    ]
    return torch.stack(losses).mean()


def voice_activity_bce(va_logit: torch.Tensor, target: torch.Tensor, sample_weight: torch.Tensor) -> torch.Tensor:
    """va_logit, target (B, T); sample_weight (B,) (e.g. 0.1 for rows not from BEAT2)."""
    per = F.binary_cross_entropy_with_logits(va_logit, target.to(va_logit.dtype), reduction="none").mean(1)
    return (per * sample_weight).mean()
