"""Token sampling of the gesture generator (MIBURI-FACTS section 3): temperature, top-p, exponential race,
classifier-free guidance, and pad masking (pad is never emitted, at any level)."""

from __future__ import annotations

import torch


def mask_pad(logits: torch.Tensor, pad_token: int) -> torch.Tensor:
    """In place: the pad logit to −inf. logits (..., V)."""
    logits[..., pad_token] = float("-inf")
    return logits


def guide(cond: torch.Tensor, null: torch.Tensor, scale: float) -> torch.Tensor:
    """Classifier-free guidance: null + scale * (cond − null)."""
    return null + scale * (cond - null)


FIRST_CANDIDATES = 128  # sort only this many first; the full sort runs when the nucleus may be larger


def top_p_probs(logits: torch.Tensor, temperature: float, top_p: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Sorted, truncated probabilities and their token ids, each (..., N) with N <= V.

    A token is kept while the cumulative probability mass *before* it is <= top_p (so the first is always kept).
    The nucleus is searched among the FIRST_CANDIDATES most probable tokens, and among all tokens when the mass
    before the last candidate is still <= top_p: the kept set is the same as with a full sort.
    """
    probs = torch.softmax(logits.float() / temperature, dim=-1)
    if probs.shape[-1] > FIRST_CANDIDATES:
        sorted_probs, order = probs.topk(FIRST_CANDIDATES, dim=-1)
        mass_before = sorted_probs.cumsum(dim=-1) - sorted_probs
        if not bool((mass_before[..., -1] <= top_p).any()):
            return sorted_probs.masked_fill(mass_before > top_p, 0.0), order
    sorted_probs, order = probs.sort(dim=-1, descending=True)
    mass_before = sorted_probs.cumsum(dim=-1) - sorted_probs
    return sorted_probs.masked_fill(mass_before > top_p, 0.0), order


def exponential_race(probs: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """Draw index i with probability probs[i] / sum(probs) as argmax(probs / E), E ~ Exp(1); (..., V) -> (...)."""
    race = torch.empty_like(probs).exponential_(generator=generator)
    return (probs / race).argmax(dim=-1)


def sample_top_p(logits: torch.Tensor, temperature: float, top_p: float,
                 generator: torch.Generator | None = None) -> torch.Tensor:
    """logits (..., V) -> token ids (...) drawn with temperature and top-p."""
    probs, order = top_p_probs(logits, temperature, top_p)
    choice = exponential_race(probs, generator)
    return order.gather(-1, choice.unsqueeze(-1)).squeeze(-1)
