"""inference_codec: a prepared copy streams like the float32 codec decodes offline; the original is untouched."""

from pathlib import Path

import pytest
import torch

from gesture.body.regions import REGION_DIMS
from gesture.codec.build import build_codec
from gesture.codec.config import load_codec_config
from gesture.codec.inference import INFERENCE_DTYPES, inference_codec
from gesture.codec.streaming import StreamingDecoder, StreamingEncoder
from tests.kernels import KERNELS, using

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
SMALL = load_codec_config(ROOT / "ecas/configs/codec/small.yaml").codec
STEPS = 30  # past the 25-step attention ring

# Largest |streamed - float32 offline| relative to max |offline|, per weight form. float32 only reorders
# sums (folded LayerScale and codebook projection, RoPE as a complex product): float32 rounding. float16
# keeps 11 significant bits (unit roundoff 2^-11 = 4.9e-4) through ~20 products in a row. bfloat16 keeps 8
# (2^-8 = 3.9e-3); int8 adds a weight error of at most max|row|/254 (4e-3 of the row's largest weight) to
# bfloat16 activations. Measured at this size: 7e-7, 7e-4, 6e-3, 9e-3.
RELATIVE_TOLERANCE = {"float32": 1e-5, "float16": 5e-3, "bfloat16": 3e-2, "int8": 5e-2}


def _codec(region: str, seed: int = 0):
    """A small-size codec with k-means codebooks and LayerScales of 0.5, so the transformer matters."""
    torch.manual_seed(seed)
    codec = build_codec(SMALL, region)
    with torch.no_grad():
        for name, parameter in codec.named_parameters():
            if name.endswith("layer_scale_1.scale") or name.endswith("layer_scale_2.scale"):
                parameter.fill_(0.5)
    codec.train()
    codec(torch.randn(4, 64, REGION_DIMS[region]))
    return codec.eval()


def _stream(codec, codes: torch.Tensor) -> torch.Tensor:
    with StreamingDecoder(codec, batch_size=codes.shape[0]) as decoder:
        return torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(codes.shape[-1])], dim=1)


@pytest.mark.parametrize("kernels", KERNELS)
@pytest.mark.parametrize("dtype", INFERENCE_DTYPES)
@pytest.mark.parametrize("region", ["upper", "face"])
def test_prepared_streaming_equals_float32_offline_decode(region, dtype, kernels):
    codec = _codec(region)
    codes = torch.randint(0, SMALL.codebook_size, (2, codec.n_q, STEPS))
    with torch.no_grad():
        offline = codec.decode(codes)
    with using(kernels, dtype):
        prepared = inference_codec(codec, dtype)
    streamed = _stream(prepared, codes)
    assert streamed.dtype == torch.float32 and streamed.shape == offline.shape
    tolerance = RELATIVE_TOLERANCE[dtype] * float(offline.abs().max())
    torch.testing.assert_close(streamed, offline, atol=tolerance, rtol=0)
    with torch.no_grad():
        torch.testing.assert_close(prepared.decode(codes), offline, atol=tolerance, rtol=0)  # offline works too


def test_prepared_float32_is_float32_exact_and_resets():
    codec = _codec("lower")
    codes = torch.randint(0, SMALL.codebook_size, (1, codec.n_q, STEPS))
    with torch.no_grad():
        offline = codec.decode(codes)
    with StreamingDecoder(codec):
        prepared = inference_codec(codec, "float32")  # copied while the original streams: no stream open
    with StreamingDecoder(prepared) as decoder:
        first = torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(STEPS)], dim=1)
        decoder.reset()
        again = torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(STEPS)], dim=1)
    torch.testing.assert_close(first, offline, atol=1e-5, rtol=0)
    assert torch.equal(first, again)
    torch.testing.assert_close(
        _stream(prepared, codes[:, :3]), codec.decode(codes[:, :3]).detach(), atol=1e-5, rtol=0
    )  # fewer levels: a coarser decode, as the original


def test_original_codec_is_untouched_and_the_encoder_half_still_works():
    codec = _codec("face").train()
    before = {k: v.clone() for k, v in codec.state_dict().items()}
    types = [type(m) for m in codec.modules()]
    prepared = inference_codec(codec, "int8")
    assert codec.training and all(p.requires_grad for p in codec.parameters())
    assert [type(m) for m in codec.modules()] == types
    assert all(torch.equal(before[k], v) for k, v in codec.state_dict().items())
    assert not prepared.training and not any(p.requires_grad for p in prepared.parameters())
    frames = torch.randn(1, 2 * STEPS, REGION_DIMS["face"])
    assert torch.equal(_encode_stream(prepared, frames), _encode_stream(codec.eval(), frames))  # float32 copy


def _encode_stream(codec, frames: torch.Tensor) -> torch.Tensor:
    with StreamingEncoder(codec) as encoder:
        return torch.cat([encoder.step(frames[:, 2 * s : 2 * s + 2]) for s in range(frames.shape[1] // 2)], dim=-1)


def test_bad_dtype_names_the_option():
    codec = _codec("face")
    with pytest.raises(ValueError, match="dtype: must be one of float32, float16, bfloat16, int8, got 'fp8'"):
        inference_codec(codec, "fp8")
