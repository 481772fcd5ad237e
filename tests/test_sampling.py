"""Token sampling: the fast top-p set equals the sort-based rule (ties, temperatures, flat and peaked rows), the
draws follow the truncated distribution, and pad is never emitted."""

import numpy as np
import pytest
import torch

from gesture.lm.sampling import draw, mask_pad, sample_top_p, tempered_probs, top_p_mask

torch.set_num_threads(1)


def sorted_rule_mask(probs: torch.Tensor, top_p: float) -> torch.Tensor:
    """The rule spelled out: stable sort by decreasing probability, keep while the mass before is <= top_p."""
    values, order = torch.sort(probs, descending=True, stable=True)
    mass_before = torch.cat([torch.zeros(1, dtype=torch.float64), values.cumsum(0, dtype=torch.float64)[:-1]])
    kept = torch.zeros_like(probs, dtype=torch.bool)
    for position, (before, token) in enumerate(zip(mass_before.tolist(), order.tolist())):
        if position > 0 and before > top_p:
            break
        kept[token] = True
    return kept


def _rows(seed: int = 0):
    """(logits (V,), what) covering flat to peaked rows, exact ties, a masked pad and tiny vocabularies."""
    g = torch.Generator().manual_seed(seed)
    for scale in (0.05, 0.5, 1.0, 3.0, 8.0, 30.0):
        for _ in range(6):
            yield torch.randn(2049, generator=g) * scale, f"gaussian x{scale}"
    for levels in (2, 5, 40):  # quantised logits: many exactly equal probabilities
        for _ in range(6):
            yield torch.randint(0, levels, (2049,), generator=g).float(), f"{levels} distinct values"
    yield torch.zeros(2049), "all equal"
    yield mask_pad(torch.randn(2049, generator=g) * 3, 2048), "pad masked"
    yield torch.tensor([0.5, 0.3, 0.15, 0.05]).log(), "4 tokens"
    yield torch.tensor([1.0, 1.0, 1.0, 0.0]), "4 tokens, 3 tied"


@pytest.mark.parametrize("temperature", [0.5, 0.9, 1.3])
@pytest.mark.parametrize("top_p", [0.0, 0.3, 0.8, 0.95, 1.0])
def test_fast_top_p_equals_the_sorted_rule(temperature, top_p):
    for logits, what in _rows():
        probs = tempered_probs(logits, temperature)
        assert torch.equal(top_p_mask(probs, top_p), sorted_rule_mask(probs, top_p)), what


def test_top_p_keeps_tokens_while_mass_before_is_at_most_p():
    probs = torch.tensor([0.5, 0.3, 0.15, 0.05])
    # mass before: 0, 0.5, 0.8, 0.95 -> keep the first three at 0.81, two at 0.79, one at 0
    assert top_p_mask(probs, 0.81).tolist() == [True, True, True, False]
    assert top_p_mask(probs, 0.79).tolist() == [True, True, False, False]
    assert top_p_mask(probs, 0.0).tolist() == [True, False, False, False]


def test_ties_at_the_boundary_keep_the_lowest_ids():
    probs = torch.tensor([0.1, 0.2, 0.2, 0.2, 0.2, 0.1])
    assert top_p_mask(probs, 0.3).tolist() == [False, True, True, False, False, False]


def test_top_p_mask_rejects_batches():
    with pytest.raises(ValueError, match="one \\(V,\\) row"):
        top_p_mask(torch.full((2, 4), 0.25), 0.5)


def test_draws_follow_the_truncated_distribution():
    probs = torch.tensor([0.5, 0.3, 0.15, 0.05])
    mask = top_p_mask(probs, 0.81)
    draws = np.array([draw(probs, mask, u) for u in np.random.default_rng(0).random(20000)])
    freq = np.bincount(draws, minlength=4) / len(draws)
    np.testing.assert_allclose(freq, np.array([0.5, 0.3, 0.15, 0.0]) / 0.95, atol=0.012, rtol=0)


def test_draw_never_returns_a_zero_probability_token_even_at_the_ends():
    probs = torch.tensor([0.0, 0.25, 0.5, 0.0])
    mask = torch.tensor([True, True, True, False])
    assert draw(probs, mask, 0.0) == 1
    assert draw(probs, mask, 0.4) == 2
    assert draw(probs, mask, 1.0) == 2  # a uniform that rounds up to the total


def test_pad_is_never_sampled_even_when_it_dominates():
    g = torch.Generator().manual_seed(0)
    for _ in range(300):
        logits = torch.zeros(17)
        logits[16] = 50.0
        assert sample_top_p(mask_pad(logits, 16), 0.9, 1.0, g) != 16


def test_same_seed_same_draws():
    logits = torch.randn(2049, generator=torch.Generator().manual_seed(1))
    a = [sample_top_p(logits, 0.9, 0.95, torch.Generator().manual_seed(5)) for _ in range(3)]
    assert len(set(a)) == 1
