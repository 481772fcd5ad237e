"""Streaming neural-network primitives shared by the gesture codecs and the gesture LM.

- `StreamingModule` / `StreamingState`: typed per-module state, `streaming(batch_size)`, `reset_streaming()`.
- `RotaryEmbedding`, `apply_rope`, `rope_frequencies`: RoPE on interleaved pairs at absolute positions (fp32).
- `RingKVCache`: the one preallocated (B, H, capacity, D) key/value ring: `append` (chunks, masked by each slot's
  absolute position) and `push` (one step, its filled slots need no mask; the codec and LM step paths).
- `attention_mask`, `windowed_attention`: causal + window masking by positions; fully masked rows -> 0.
- `StreamingMultiheadAttention`, `StreamingTransformer(Layer)`: packed-q/k/v pre-LN causal transformer.
- `StreamingConv1d`, `StreamingConvTranspose1d`: causal weight-normed convs, streaming == offline.
"""

from gesture.nn.attention import StreamingMultiheadAttention, attention_mask, windowed_attention
from gesture.nn.conv import StreamingConv1d, StreamingConvTranspose1d
from gesture.nn.kv_cache import RingKVCache
from gesture.nn.rope import RotaryEmbedding, apply_rope, rope_frequencies
from gesture.nn.streaming import StreamingModule, StreamingState
from gesture.nn.transformer import LayerScale, StreamingTransformer, StreamingTransformerLayer

__all__ = [
    "LayerScale",
    "RingKVCache",
    "RotaryEmbedding",
    "StreamingConv1d",
    "StreamingConvTranspose1d",
    "StreamingModule",
    "StreamingMultiheadAttention",
    "StreamingState",
    "StreamingTransformer",
    "StreamingTransformerLayer",
    "apply_rope",
    "attention_mask",
    "rope_frequencies",
    "windowed_attention",
]
