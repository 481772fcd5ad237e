"""RVQ with EMA codebooks: k-means init, EMA learning, dead-code replacement, dropout, no-quantization."""

import pytest
import torch

from gesture.codec.quantizer import EuclideanCodebook, ResidualVectorQuantizer, kmeans

torch.set_num_threads(1)


def _clusters(n_per=50, centers=((0.0, 0.0), (10.0, 0.0), (0.0, 10.0)), seed=0):
    g = torch.Generator().manual_seed(seed)
    points = [torch.tensor(c) + 0.1 * torch.randn(n_per, 2, generator=g) for c in centers]
    return torch.cat(points)


def test_kmeans_finds_separated_clusters():
    torch.manual_seed(1)
    centroids, counts = kmeans(_clusters(), 3, iters=20)
    found = sorted(tuple(round(v) for v in c.tolist()) for c in centroids)
    assert found == [(0, 0), (0, 10), (10, 0)]
    assert sorted(counts.tolist()) == [50.0, 50.0, 50.0]


def _codebook(size=3, decay=0.9, every=1000):
    return EuclideanCodebook(
        dim=2, codebook_size=size, decay=decay, kmeans_iters=20, dead_code_every_steps=every, dead_code_usage_ratio=0.1
    )


def test_codebook_initialises_once_then_learns_by_ema():
    torch.manual_seed(1)
    codebook = _codebook().train()
    x = _clusters()
    quantized, codes = codebook(x)
    assert codebook.initialized and codebook._initialized.tolist() == [1.0]
    assert (quantized - x).abs().max() < 0.5
    shifted = x + torch.tensor([1.0, 1.0])
    before = codebook.embedding.clone()
    for _ in range(60):
        codebook(shifted)
    moved = codebook.embedding - before
    torch.testing.assert_close(moved, torch.ones(3, 2), atol=0.05, rtol=0)  # EMA tracked the shift
    torch.testing.assert_close(codebook.embedding, codebook.embedding_sum / codebook.cluster_usage[:, None])


def test_dead_codes_are_replaced_with_batch_vectors():
    torch.manual_seed(0)
    codebook = _codebook(size=4, decay=0.5, every=5).train()
    x = _clusters(centers=((0.0, 0.0), (10.0, 0.0)))
    codebook.initialize(x)
    codebook.embedding_sum[3] = torch.tensor([1000.0, 1000.0]) * codebook.cluster_usage[3]  # never used
    for _ in range(5):
        codebook(x)
    far = (codebook.embedding - torch.tensor([1000.0, 1000.0])).norm(dim=-1)
    assert far.min() > 100  # the unused code now sits on a data vector
    assert codebook.embedding[3].norm() < 12


def _rvq(**kwargs):
    torch.manual_seed(0)
    return ResidualVectorQuantizer(dim=6, codebook_dim=4, n_q=4, codebook_size=16, kmeans_iters=5, **kwargs)


def test_residual_levels_reduce_the_error():
    rvq = _rvq().train()
    z = torch.randn(8, 6, 10)
    rvq(z)
    rvq.eval()
    target = rvq.input_proj(z).transpose(1, 2)  # (B, S, Dq)
    codes = rvq.encode(z)
    errors = []
    for k in range(1, 5):
        approx = sum(cb.decode(codes[:, i]) for i, cb in enumerate(rvq._codebooks()[:k]))
        errors.append(float((approx - target).pow(2).mean().detach()))
    assert errors == sorted(errors, reverse=True) and errors[-1] < 0.5 * errors[0]


def test_quantizer_dropout_uses_1_to_n_q_levels():
    rvq = _rvq(quantizer_dropout=True).train()
    used = {rvq(torch.randn(2, 6, 5)).codes.shape[1] for _ in range(60)}
    assert used == {1, 2, 3, 4}
    assert rvq.eval()(torch.randn(2, 6, 5)).codes.shape[1] == 4


def test_no_quantization_rate_passes_the_projection_through():
    rvq = _rvq(no_quantization_rate=1.0).train()
    z = torch.randn(3, 6, 100)  # 300 vectors for 16 codes: quantizing loses something
    out = rvq(z)
    torch.testing.assert_close(out.quantized, rvq.output_proj(rvq.input_proj(z)))
    assert rvq.eval()(z).quantized.sub(out.quantized).abs().max() > 1e-3


def test_straight_through_gradient_and_commitment_loss():
    rvq = _rvq().train()
    z = torch.randn(2, 6, 5, requires_grad=True)
    out = rvq(z)
    assert out.commitment_loss > 0
    (out.quantized.sum() + out.commitment_loss).backward()
    assert z.grad is not None and z.grad.abs().sum() > 0
    assert rvq.input_proj.weight.grad.abs().sum() > 0


def test_decode_rejects_too_many_levels():
    rvq = _rvq().eval()
    with pytest.raises(ValueError, match="K<=4"):
        rvq.decode(torch.zeros(1, 5, 2, dtype=torch.long))
