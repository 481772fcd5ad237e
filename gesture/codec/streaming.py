"""Step-by-step codec inference: one step = FRAMES_PER_STEP frames (80 ms) <-> one column of codes.

    decoder = StreamingDecoder(codec, batch_size=1)
    frames = decoder.step(codes)      # (B, K, 1) -> (B, 2, nfeats)
    encoder = StreamingEncoder(codec)
    codes = encoder.step(frames)      # (B, 2, nfeats) -> (B, n_q, 1)

Both run in `torch.inference_mode` and own the streaming states of their half of the codec (the
encoder half and the decoder half are disjoint, so one codec can serve both at once). Stream
outputs equal the offline `codec.encode` / `codec.decode` of the whole sequence; `reset()` starts a
new stream; `close()` returns the modules to offline mode.
"""

from __future__ import annotations

import torch

from ecas.core.timing import FRAMES_PER_STEP
from gesture.codec.model import GestureCodec
from gesture.nn import StreamingModule


class _CodecHalf:
    def __init__(self, codec: GestureCodec, modules: tuple[StreamingModule, ...], batch_size: int) -> None:
        if codec.ratio != FRAMES_PER_STEP:
            raise ValueError(
                f"streaming needs a codec with ratio {FRAMES_PER_STEP} (frames per step), got {codec.ratio}"
            )
        if codec.training:
            raise ValueError("streaming needs an eval-mode codec: call codec.eval() first")
        self.codec, self.batch_size, self._modules = codec, batch_size, modules
        for module in modules:
            if module.is_streaming:
                raise RuntimeError(f"{type(module).__name__} is already streaming; close the other stream first")
            module.start_streaming(batch_size)

    def reset(self) -> None:
        for module in self._modules:
            module.reset_streaming()

    def close(self) -> None:
        for module in self._modules:
            module.stop_streaming()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class StreamingDecoder(_CodecHalf):
    """codes (B, K, 1) per step -> (B, FRAMES_PER_STEP, nfeats) float32.

    For speed, decode with a prepared copy, `gesture.codec.inference.inference_codec(codec, "int8")` (or
    "float32", "float16", "bfloat16"; see bench/codec.py and tests/test_codec_inference.py); a codec cast
    with `codec.half()` also works."""

    def __init__(self, codec: GestureCodec, batch_size: int = 1) -> None:
        super().__init__(codec, (codec.transformer_decoder, codec.seanet_decoder), batch_size)

    @torch.inference_mode()
    def step(self, codes: torch.Tensor) -> torch.Tensor:
        if codes.dim() != 3 or codes.shape[0] != self.batch_size or codes.shape[2] != 1:
            raise ValueError(f"codes must be ({self.batch_size}, K, 1), got {tuple(codes.shape)}")
        return self.codec.decode(codes).float()


class StreamingEncoder(_CodecHalf):
    """(B, FRAMES_PER_STEP, nfeats) per step -> codes (B, n_q, 1)."""

    def __init__(self, codec: GestureCodec, batch_size: int = 1) -> None:
        super().__init__(codec, (codec.seanet_encoder, codec.transformer_encoder), batch_size)

    @torch.inference_mode()
    def step(self, frames: torch.Tensor) -> torch.Tensor:
        expected = (self.batch_size, FRAMES_PER_STEP, self.codec.nfeats)
        if tuple(frames.shape) != expected:
            raise ValueError(f"frames must be {expected}, got {tuple(frames.shape)}")
        return self.codec.encode(frames)
