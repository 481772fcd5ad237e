"""The shipped small codecs (ecas/checkpoints/codec_small): they load, stream, and reconstruct the held-out
last 10 s of the real BEAT2 clip as well as when they were trained (values pinned from the model card)."""

from pathlib import Path

import pytest
import torch

from ecas.core.paths import CHECKPOINTS_DIR, data_root
from gesture.body.skeleton import Skeleton
from gesture.codec.checkpoint import load_codec
from gesture.codec.data import load_motion_splits
from gesture.codec.evaluation import evaluate
from gesture.codec.streaming import StreamingDecoder

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
CHECKPOINTS = CHECKPOINTS_DIR / "codec_small"
CLIP = data_root() / "beat2" / "2_scott_0_1_1.npz"
# held-out errors measured after training (README.md of the checkpoints), with a margin for float noise
HELDOUT_LIMITS = {"upper": ("mpjpe_mm", 75.0), "lower": ("mpjpe_mm", 20.0), "face": ("jaw_error_deg", 1.2)}


@pytest.fixture(scope="module")
def heldout():
    if not CLIP.is_file():
        pytest.skip("needs ../shared/data/beat2")
    return load_motion_splits(CLIP, holdout_seconds=10.0)[1]


@pytest.mark.parametrize("region", ["upper", "lower", "face"])
def test_shipped_codec_reconstructs_the_held_out_clip(region, heldout):
    codec = load_codec(CHECKPOINTS / region)
    metric, limit = HELDOUT_LIMITS[region]
    result = evaluate(codec, heldout, region, Skeleton.default())
    assert result["frames"] == 250
    assert result[metric] < limit, result


def test_shipped_codec_streams_like_offline(heldout):
    codec = load_codec(CHECKPOINTS / "upper")
    codes = codec.encode(heldout[0].features["upper"][None, :80])  # (1, 8, 40)
    with StreamingDecoder(codec) as decoder:
        streamed = torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(40)], dim=1)
    torch.testing.assert_close(streamed, codec.decode(codes), atol=1e-5, rtol=0)
