"""Gesture codecs: reference sizes and key names, streaming == offline, causality, RVQ round trip."""

from pathlib import Path

import pytest
import torch

from ecas.core.config import ConfigError
from gesture.body.regions import REGION_DIMS
from gesture.codec.build import build_codec, count_parameters
from gesture.codec.config import CodecConfig, RegionSizes, codec_file_config_from_dict, load_codec_config
from gesture.codec.streaming import StreamingDecoder, StreamingEncoder

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
KEYS_DIR = ROOT.parent / "shared" / "reference" / "state_dict_keys"
TINY = CodecConfig(
    latent_dim=32,
    n_filters=16,
    dim_feedforward=64,
    context_steps=4,
    codebook_size=32,
    codebook_dim=8,
    kmeans_iters=5,
    dropout=0.0,
    regions={"upper": RegionSizes(3, 2, 2), "lower": RegionSizes(3, 2, 2), "face": RegionSizes(2, 1, 2)},
)


def _trained_like(region: str, config: CodecConfig = TINY, seed: int = 0):
    """A tiny codec whose codebooks were k-means initialised on its own latents, in eval mode."""
    torch.manual_seed(seed)
    codec = build_codec(config, region)
    x = torch.randn(4, 40, REGION_DIMS[region])
    codec.train()
    codec(x)
    return codec.eval(), x


@pytest.mark.parametrize("region,expected", [("upper", 27_515_148), ("lower", 26_808_706), ("face", 15_415_256)])
def test_reference_size_parameter_count_and_official_keys(region, expected):
    codec = build_codec(CodecConfig(), region)
    assert count_parameters(codec) == expected  # 27.5M / 26.8M / 15.4M
    rows = [line.split("\t") for line in (KEYS_DIR / f"codec_{region}.tsv").read_text().splitlines() if line]
    official = {key: tuple(int(d) for d in shape.strip("()\n").split(",") if d.strip()) for key, shape in rows}
    assert {k: tuple(v.shape) for k, v in codec.state_dict().items()} == official
    fake = {k: torch.randn(shape) for k, shape in official.items()}
    codec.load_state_dict(fake, strict=True)


def test_reference_yaml_is_the_default_config():
    assert load_codec_config(ROOT / "ecas/configs/codec/reference.yaml").codec == CodecConfig()
    load_codec_config(ROOT / "ecas/configs/codec/small.yaml")


def test_bad_options_name_the_option():
    with pytest.raises(ConfigError, match="codec.codebook_size"):
        codec_file_config_from_dict({"codec": {"codebook_size": 0}})
    with pytest.raises(ConfigError, match="codec.regions.face: missing"):
        codec_file_config_from_dict(
            {
                "codec": {
                    "regions": {
                        "upper": {"n_q": 8, "num_layers": 8, "num_heads": 4},
                        "lower": {"n_q": 8, "num_layers": 8, "num_heads": 4},
                    }
                }
            }
        )
    with pytest.raises(ConfigError, match="codec.regions.face.n_q: must be > 0"):
        codec_file_config_from_dict(
            {
                "codec": {
                    "regions": {
                        r: {"n_q": 0 if r == "face" else 8, "num_layers": 1, "num_heads": 2}
                        for r in ("upper", "lower", "face")
                    }
                }
            }
        )
    with pytest.raises(ConfigError, match="train.window_frames"):
        codec_file_config_from_dict({"train": {"window_frames": 7}})
    with pytest.raises(ConfigError, match="region"):
        CodecConfig().region("hands")


def test_offline_shapes_and_bad_inputs():
    codec, x = _trained_like("face")
    codes = codec.encode(x)
    assert codes.shape == (4, 2, 20) and codes.dtype == torch.long and int(codes.max()) < TINY.codebook_size
    assert codec.decode(codes).shape == x.shape
    assert codec.decode(codes[:, :1]).shape == x.shape  # coarser decode from fewer levels
    with pytest.raises(ValueError, match="multiple of 2"):
        codec.encode(x[:, :5])
    with pytest.raises(ValueError, match=r"\(B, T, 106\)"):
        codec.encode(x[..., :10])


@pytest.mark.parametrize("region", ["upper", "lower", "face"])
def test_streaming_decoder_equals_offline_past_the_cache(region):
    codec, x = _trained_like(region)
    codes = codec.encode(x)  # (4, K, 20): 20 steps, context 4 -> the ring wraps several times
    offline = codec.decode(codes)
    with StreamingDecoder(codec, batch_size=4) as decoder:
        streamed = torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(codes.shape[-1])], dim=1)
        decoder.reset()
        again = torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(5)], dim=1)
    assert streamed.shape == (4, 40, REGION_DIMS[region])
    torch.testing.assert_close(streamed, offline, atol=1e-5, rtol=0)
    torch.testing.assert_close(again, offline[:, :10], atol=1e-5, rtol=0)


def test_streaming_encoder_equals_offline_and_both_halves_stream_together():
    codec, x = _trained_like("upper")
    offline_codes = codec.encode(x)
    offline_frames = codec.decode(offline_codes)
    with StreamingEncoder(codec, batch_size=4) as encoder, StreamingDecoder(codec, batch_size=4) as decoder:
        steps = [encoder.step(x[:, 2 * s : 2 * s + 2]) for s in range(20)]
        frames = torch.cat([decoder.step(c) for c in steps], dim=1)
    assert torch.equal(torch.cat(steps, dim=-1), offline_codes)
    torch.testing.assert_close(frames, offline_frames, atol=1e-5, rtol=0)
    assert not codec.seanet_encoder.is_streaming and not codec.transformer_decoder.is_streaming


def test_streaming_at_small_size_with_the_25_step_context():
    config = load_codec_config(ROOT / "ecas/configs/codec/small.yaml").codec
    codec, _ = _trained_like("lower", config)
    codes = torch.randint(0, config.codebook_size, (1, 8, 30))  # 30 steps > 25-step ring
    offline = codec.decode(codes)
    with StreamingDecoder(codec) as decoder:
        streamed = torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(30)], dim=1)
    torch.testing.assert_close(streamed, offline, atol=1e-5, rtol=0)


def test_half_precision_streaming_stays_close_to_float32():
    codec, x = _trained_like("upper")
    codes = codec.encode(x)
    offline = codec.decode(codes)
    with StreamingDecoder(codec.half(), batch_size=4) as decoder:
        streamed = torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(codes.shape[-1])], dim=1)
    assert streamed.dtype == torch.float32
    torch.testing.assert_close(streamed, offline, atol=2e-2, rtol=0)


def test_appending_input_never_changes_earlier_output():
    codec, x = _trained_like("lower")
    codes = codec.encode(x)
    longer = torch.cat([x, torch.randn(4, 10, x.shape[-1]) * 5], dim=1)
    assert torch.equal(codec.encode(longer)[..., :20], codes)
    more_codes = torch.cat([codes, torch.randint(0, TINY.codebook_size, (4, 3, 7))], dim=-1)
    torch.testing.assert_close(codec.decode(more_codes)[:, :40], codec.decode(codes), atol=1e-6, rtol=0)


def test_encode_then_decode_is_exact_on_the_quantized_latents():
    codec, x = _trained_like("upper")
    latent = codec.encode_latent(x)
    quantized = codec.quantizer(latent).quantized  # eval: every level, no dropout, no skipping
    torch.testing.assert_close(codec.quantizer.decode(codec.quantizer.encode(latent)), quantized, atol=1e-6, rtol=0)
    torch.testing.assert_close(codec.decode(codec.encode(x)), codec(x).reconstruction, atol=1e-6, rtol=0)


def test_streaming_refuses_a_training_codec_and_bad_steps():
    codec = build_codec(TINY, "face")
    with pytest.raises(ValueError, match="eval"):
        StreamingDecoder(codec)
    codec.eval()
    with StreamingDecoder(codec) as decoder:
        with pytest.raises(ValueError, match=r"\(1, K, 1\)"):
            decoder.step(torch.zeros(1, 2, 3, dtype=torch.long))
        with pytest.raises(RuntimeError, match="already streaming"):
            StreamingDecoder(codec)
