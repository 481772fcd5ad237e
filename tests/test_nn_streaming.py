"""gesture.nn: RoPE, ring KV cache, windowed attention, streaming convs and transformer."""

import math

import pytest
import torch

from gesture.nn import (
    RingKVCache,
    RotaryEmbedding,
    StreamingConv1d,
    StreamingConvTranspose1d,
    StreamingTransformer,
    attention_mask,
    windowed_attention,
)

torch.set_num_threads(1)


def test_rope_known_rotation_and_fp32_angles():
    rope = RotaryEmbedding(head_dim=4, period=10_000.0)
    x = torch.tensor([1.0, 0.0, 1.0, 0.0]).view(1, 1, 1, 4)
    y = rope.rotate(x, torch.tensor([3]))
    # pair 0 has frequency 1, pair 1 has 10000^(-2/4) = 0.01
    expected = torch.tensor([math.cos(3), math.sin(3), math.cos(0.03), math.sin(0.03)])
    torch.testing.assert_close(y.flatten(), expected, rtol=0, atol=1e-6)
    big = rope.rotate(x.to(torch.bfloat16), torch.tensor([100_000]))
    assert big.dtype == torch.bfloat16
    torch.testing.assert_close(
        big.float().flatten()[:2], torch.tensor([math.cos(1e5), math.sin(1e5)]), atol=1e-2, rtol=0
    )


def test_rope_scores_depend_only_on_relative_position():
    torch.manual_seed(0)
    rope = RotaryEmbedding(head_dim=8)
    q, k = torch.randn(1, 1, 1, 8), torch.randn(1, 1, 1, 8)
    scores = [(rope.rotate(q, torch.tensor([t + 5])) * rope.rotate(k, torch.tensor([t]))).sum() for t in (0, 17, 900)]
    torch.testing.assert_close(torch.stack(scores), scores[0].expand(3), atol=1e-4, rtol=0)


def test_ring_kv_cache_wraps_and_keeps_positions():
    cache = RingKVCache(batch_size=1, num_heads=1, head_dim=1, capacity=3)
    for t in range(4):
        keys, values, positions = cache.append(torch.full((1, 1, 1, 1), float(t)), torch.full((1, 1, 1, 1), -float(t)))
    assert positions.tolist() == [3, 1, 2]
    assert keys.flatten().tolist() == [3.0, 1.0, 2.0]
    keys, _, positions = cache.append(torch.arange(2.0).view(1, 1, 2, 1) + 10, torch.zeros(1, 1, 2, 1))
    assert positions.tolist() == [3, 4, 5] and keys.flatten().tolist() == [3.0, 10.0, 11.0]
    storage = cache.keys.data_ptr()
    cache.reset()
    assert cache.positions.tolist() == [-1, -1, -1] and cache.next_position == 0 and cache.keys.data_ptr() == storage
    with pytest.raises(ValueError, match="capacity 3"):
        cache.append(torch.zeros(1, 1, 4, 1), torch.zeros(1, 1, 4, 1))


def test_attention_mask_causal_window_and_empty_slots():
    allowed = attention_mask(torch.tensor([2, 3]), torch.tensor([3, 1, 2, -1]), context=2)
    assert allowed.tolist() == [[False, True, True, False], [True, False, True, False]]
    both = attention_mask(torch.tensor([0, 5]), torch.tensor([1, 2]), context=None, causal=False)
    assert both.all()


def test_fully_masked_rows_are_zero_not_nan():
    torch.manual_seed(0)
    q, k, v = torch.randn(2, 2, 3, 4), torch.randn(2, 2, 5, 4), torch.randn(2, 2, 5, 4)
    allowed = torch.zeros(2, 3, 5, dtype=torch.bool)
    allowed[:, 1, :2] = True
    out = windowed_attention(q, k, v, allowed)
    assert torch.isfinite(out).all()
    assert out[:, :, 0].abs().max() == 0 and out[:, :, 2].abs().max() == 0
    assert out[:, :, 1].abs().max() > 0


def _stream(module, x, chunk):
    with module.streaming(batch_size=x.shape[0]):
        return torch.cat([module(x[..., i : i + chunk]) for i in range(0, x.shape[-1], chunk)], dim=-1)


@pytest.mark.parametrize("kernel,stride,dilation,chunk", [(7, 1, 1, 1), (3, 1, 2, 2), (4, 2, 1, 2), (4, 2, 1, 6)])
def test_streaming_conv_equals_offline_and_is_causal(kernel, stride, dilation, chunk):
    torch.manual_seed(0)
    conv = StreamingConv1d(3, 5, kernel, stride, dilation)
    x = torch.randn(2, 3, 24)
    offline = conv(x)
    assert offline.shape == (2, 5, 24 // stride)
    torch.testing.assert_close(_stream(conv, x, chunk), offline, atol=1e-5, rtol=0)
    changed = x.clone()
    changed[..., 12:] = torch.randn(2, 3, 12)
    torch.testing.assert_close(conv(changed)[..., : 12 // stride], offline[..., : 12 // stride], atol=0, rtol=0)


def test_streaming_conv_transpose_equals_offline():
    torch.manual_seed(0)
    convtr = StreamingConvTranspose1d(4, 3, kernel_size=4, stride=2)
    x = torch.randn(2, 4, 10)
    offline = convtr(x)
    assert offline.shape == (2, 3, 20)
    torch.testing.assert_close(_stream(convtr, x, 1), offline, atol=1e-5, rtol=0)
    torch.testing.assert_close(convtr(x[..., :6]), offline[..., :12], atol=1e-6, rtol=0)


def test_weight_norm_keys_and_fold_follows_loaded_weights():
    conv = StreamingConv1d(3, 2, 3)
    assert sorted(conv.state_dict()) == ["conv.conv.bias", "conv.conv.weight_g", "conv.conv.weight_v"]
    convtr = StreamingConvTranspose1d(6, 4, 4, 2)
    assert convtr.state_dict()["convtr.convtr.weight_g"].shape == (6, 1, 1)
    x = torch.randn(1, 3, 8)
    with torch.inference_mode():
        before = conv(x)
    state = {k: v * 2 for k, v in conv.state_dict().items()}
    conv.load_state_dict(state)
    with torch.inference_mode():
        after = conv(x)
    torch.testing.assert_close(
        after - state["conv.conv.bias"][:, None], 2 * (before - state["conv.conv.bias"][:, None] / 2), atol=1e-5, rtol=0
    )


def test_streaming_transformer_equals_offline_past_the_context_and_resets():
    torch.manual_seed(0)
    model = StreamingTransformer(d_model=16, num_heads=2, num_layers=2, dim_feedforward=32, context=5).eval()
    x = torch.randn(2, 13, 16)
    offline = model(x)
    with torch.no_grad(), model.streaming(batch_size=2):
        first = torch.cat([model(x[:, t : t + 1]) for t in range(13)], dim=1)
        model.reset_streaming()
        second = torch.cat([model(x[:, t : t + 1]) for t in range(13)], dim=1)
    torch.testing.assert_close(first, offline, atol=1e-5, rtol=0)
    torch.testing.assert_close(second, offline, atol=1e-5, rtol=0)
    # the window: steps more than `context` back have no influence
    changed = x.clone()
    changed[:, :3] = torch.randn(2, 3, 16)
    torch.testing.assert_close(model(changed)[:, 3 + 2 * 4 :], offline[:, 3 + 2 * 4 :], atol=1e-5, rtol=0)
    assert not torch.allclose(model(changed)[:, 3], offline[:, 3])


def test_streaming_attention_rejects_oversized_chunks():
    model = StreamingTransformer(d_model=8, num_heads=2, num_layers=1, dim_feedforward=8, context=4)
    with model.streaming(batch_size=1), pytest.raises(ValueError, match="at most 1 steps"):
        model(torch.zeros(1, 2, 8))
