"""The small causal speech tokenizer: streaming == offline, causality, and the shipped checkpoint's quality."""

import json

import numpy as np
import pytest
import torch

from dialogue.speech_tokenizer import DEFAULT_CHECKPOINT, SpeechTokenizer, StreamingSpeechEncoder, TokenizerShape
from dialogue.text_vocab import LOCAL_SPEC
from dialogue.train_speech_tokenizer import mean_baseline_l1, reconstruction_l1
from tests.dialogue_helpers import LIBRIVOX, load_24k


@pytest.fixture(scope="module")
def shipped():
    return SpeechTokenizer.load(DEFAULT_CHECKPOINT)


@pytest.fixture(scope="module")
def speech():
    x = load_24k(LIBRIVOX)
    return x[: len(x) // 1920 * 1920]


def test_streaming_codes_equal_offline_codes(shipped, speech):
    offline = shipped.encode(torch.from_numpy(speech)[None])[0].numpy()  # (8, S)
    stream = StreamingSpeechEncoder(shipped)
    streamed = np.stack([stream.step(speech[i : i + 1920]) for i in range(0, len(speech), 1920)], -1)
    assert streamed.shape == offline.shape == (8, len(speech) // 1920)
    np.testing.assert_array_equal(streamed, offline)


def test_streaming_latent_equals_offline_within_1e5(shipped, speech):
    x = torch.from_numpy(speech[: 1920 * 20])[None]
    padded = torch.nn.functional.pad(x, (shipped.history_samples(), 0))
    with torch.no_grad():
        full, _ = shipped.encode_latent(shipped.step_features(padded))
        hidden, pieces = None, []
        for s in range(20):
            chunk = padded[:, s * 1920 : (s + 1) * 1920 + shipped.history_samples()]
            latent, hidden = shipped.encode_latent(shipped.step_features(chunk), hidden)
            pieces.append(latent)
    torch.testing.assert_close(torch.cat(pieces, 1), full, atol=1e-5, rtol=0)


def test_appending_audio_never_changes_earlier_codes(shipped, speech):
    short = shipped.encode(torch.from_numpy(speech[: 1920 * 30])[None])
    extended = np.concatenate([speech[: 1920 * 30], np.ones(1920 * 5, np.float32)])
    longer = shipped.encode(torch.from_numpy(extended)[None])
    torch.testing.assert_close(longer[..., :30], short)


def test_shipped_checkpoint_reconstructs_held_out_real_speech(shipped, speech):
    assert shipped.shape == TokenizerShape() and shipped.shape.bins == LOCAL_SPEC.audio_card
    codes = shipped.encode(torch.from_numpy(speech)[None])
    assert int(codes.min()) >= 0 and int(codes.max()) < LOCAL_SPEC.audio_card
    l1_8 = reconstruction_l1(shipped, speech, 8)
    l1_1 = reconstruction_l1(shipped, speech, 1)
    assert l1_8 < l1_1 < mean_baseline_l1(shipped, speech)
    assert l1_8 < 0.6 * mean_baseline_l1(shipped, speech)
    usage = [len(np.unique(level)) for level in codes[0].numpy()]
    assert min(usage) > 20  # every level is in use


def test_checkpoint_records_its_training(shipped):
    from safetensors import safe_open

    with safe_open(str(DEFAULT_CHECKPOINT), "pt") as f:
        info = json.loads(f.metadata()["training"])
    assert info["iterations"] > 0 and "librivox_0870 (real, held out)" in info["metrics"]


def test_missing_checkpoint_and_bad_step_are_clear_errors(tmp_path, shipped):
    with pytest.raises(FileNotFoundError, match="train one with"):
        SpeechTokenizer.load(tmp_path / "nope.safetensors")
    with pytest.raises(ValueError, match=r"\(1920,\)"):
        StreamingSpeechEncoder(shipped).step(np.zeros(100, np.float32))


def test_rvq_encode_recovers_first_level_codes(shipped):
    codes = torch.randint(0, 256, (5, 8))
    latent = shipped.rvq.decode(codes)
    assert latent.shape == (5, shipped.shape.latent)
    np.testing.assert_array_equal(shipped.rvq.encode(shipped.rvq.decode(codes[:, :1], 1))[:, 0], codes[:, 0])
