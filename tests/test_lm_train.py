"""Gesture LM training: loss terms, schedules, data contract, a short run that learns and resumes."""

import json

import numpy as np
import pytest
import torch

from ecas.core.config import ConfigError
from gesture.lm.config import LMFileConfig, LMTrainConfig
from gesture.lm.data import LMDataset, write_recording, write_spec
from gesture.lm.losses import level_weights, segment_info_nce, token_ce
from gesture.lm.schedule import condition_drop_probability, drop_conditions, gumbel_tau, pad_input_rate, pad_inputs
from gesture.lm.train import main, train
from tests.lm_fixtures import TINY_SPEC, tiny_lm_config

torch.set_num_threads(1)
REFERENCE = LMTrainConfig()


def test_level_weights_follow_the_reference():
    w = level_weights(20, range(16, 20), 2.5)
    assert torch.allclose(w[:16], torch.full((16,), 0.05)) and torch.allclose(w[16:], torch.full((4,), 0.125))


def test_token_ce_ignores_pad_targets():
    logits = torch.zeros(1, 2, 2, 5)
    logits[0, 0, 0, 1] = 10.0  # confident and right at (t0, k0)
    targets = torch.tensor([[[1, 4], [2, 4]]])  # (B, K, T); pad = 4
    weights = torch.tensor([1.0, 1.0])
    loss = token_ce(logits, targets, weights, pad_token=4)
    expected_k0 = torch.nn.functional.cross_entropy(logits[0, 0, 0], torch.tensor(1))  # only t0 counts
    expected_k1 = np.log(5)
    assert abs(float(loss) - float(expected_k0 + expected_k1)) < 1e-5


def test_info_nce_prefers_matching_segments():
    x = torch.randn(3, 24, 8)
    matched = segment_info_nce(x, x, 12, 0.1)
    shuffled = segment_info_nce(x, x.roll(1, dims=0), 12, 0.1)
    assert matched < 0.1 < shuffled


def test_schedules_at_the_reference_epochs():
    assert condition_drop_probability(10, REFERENCE) == 1.0
    assert condition_drop_probability(50, REFERENCE) == 1.0
    assert abs(condition_drop_probability(75, REFERENCE) - 0.55) < 1e-9
    assert condition_drop_probability(400, REFERENCE) == pytest.approx(0.1)
    assert pad_input_rate(99, REFERENCE) == 0.0 and pad_input_rate(150, REFERENCE) == pytest.approx(0.05)
    assert pad_input_rate(500, REFERENCE) == pytest.approx(0.1)
    assert gumbel_tau(0, REFERENCE) == 1.0 and gumbel_tau(52.5, REFERENCE) == pytest.approx(0.7)
    assert gumbel_tau(60, REFERENCE) == pytest.approx(0.4)


def test_condition_dropout_and_pad_inputs():
    g = torch.Generator().manual_seed(0)
    text, audio = torch.ones(1000, 3, dtype=torch.long), torch.ones(1000, 8, 3, dtype=torch.long)
    t, a = drop_conditions(text, audio, 0.3, g)
    dropped_t, dropped_a = (t[:, 0] == -1).float().mean(), (a[:, 0, 0] == -1).float().mean()
    assert abs(dropped_t - 0.3) < 0.05 and abs(dropped_a - 0.3) < 0.05
    assert ((t == -1).all(1) | (t == 1).all(1)).all()
    assert (t[:, 0] == -1).float().mul(a[:, 0, 0] == -1).mean() < 0.15  # independent, not together
    sizes = tiny_lm_config()
    tokens = torch.zeros(1000, 20, 4, dtype=torch.long)
    padded = pad_inputs(tokens, sizes, 0.1, g)
    chosen = padded[:, 8, 0] == sizes.pad_token
    assert abs(chosen.float().mean() - 0.1) < 0.03
    assert (padded[:, :8] == 0).all() and (padded[chosen, 8:] == sizes.pad_token).all()


def _dataset(tmp_path, steps=60, n=3, spec=TINY_SPEC):
    data = tmp_path / "data"
    data.mkdir()
    write_spec(data, spec)
    rng = np.random.default_rng(0)
    base = rng.integers(0, 16, (20, 6))
    for i in range(n):  # a learnable pattern: tokens repeat with period 6, conditioned on the text token
        tokens = np.tile(base, steps // 6)
        text = np.tile(np.arange(6), steps // 6)
        write_recording(
            data / f"r{i}.npz",
            tokens,
            text,
            rng.integers(0, spec.audio_card, (8, steps)),
            (text % 2).astype(np.uint8),
            speaker=i,
        )
    return data


def _tiny_file_config(**train):
    base = dict(
        batch_size=4,
        window_steps=24,
        epochs=4,
        steps_per_epoch=5,
        warmup_epochs=1,
        cond_drop_end_epoch=2,
        pad_start_epoch=2,
        pad_full_epoch=3,
        tau_epochs=1,
        lr=3e-3,
        checkpoint_every_epochs=2,
    )
    return LMFileConfig(lm=tiny_lm_config(), condition=TINY_SPEC, train=LMTrainConfig(**{**base, **train}))


def test_short_training_learns_and_resumes(tmp_path):
    data = _dataset(tmp_path)
    out = tmp_path / "out"
    history = train(_tiny_file_config(epochs=2), data, out, progress=False)
    assert len(history) == 2 and {"ce", "infonce", "va", "total"} <= set(history[0])
    assert (out / "lm.safetensors").exists() and (out / "loss_curve.png").exists()
    resumed = train(_tiny_file_config(epochs=4), data, out, progress=False)
    assert resumed[:2] == history and len(resumed) == 4
    assert resumed[-1]["ce"] < resumed[0]["ce"]
    assert json.loads((out / "lm.json").read_text())["epoch"] == 4


def test_dataset_rejects_a_foreign_spec_and_bad_files(tmp_path):
    from ecas.core.spec import MOSHI_SPEC, SpecMismatchError

    data = _dataset(tmp_path)
    with pytest.raises(SpecMismatchError):
        LMDataset(data, 20, MOSHI_SPEC)
    np.savez(data / "bad.npz", gesture_tokens=np.zeros((20, 5)))
    with pytest.raises(ValueError, match="missing key text_tokens"):
        LMDataset(data, 20, TINY_SPEC)


def test_train_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="train.window_steps"):
        LMTrainConfig(window_steps=6)


@pytest.mark.slow
def test_cli_trains_the_small_config(tmp_path):
    from ecas.core.spec import ConditionSpec

    data = _dataset(tmp_path, steps=120, spec=ConditionSpec("local-v1", 8192, 256, 256))
    main(
        [
            "--config",
            "ecas/configs/lm/small.yaml",
            "--data",
            str(data),
            "--out",
            str(tmp_path / "out"),
            "--epochs",
            "2",
            "--no-progress",
        ]
    )
    assert (tmp_path / "out" / "loss_curve.png").exists()


def test_zero_infonce_weight_leaves_the_term_out(tmp_path):
    history = train(
        _tiny_file_config(epochs=1, infonce_weight=0.0, va_weight=0.2),
        _dataset(tmp_path),
        tmp_path / "out",
        progress=False,
    )
    assert "infonce" not in history[0]
    assert history[0]["total"] == pytest.approx(history[0]["ce"] + 0.2 * history[0]["va"], rel=1e-5)
