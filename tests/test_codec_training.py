"""Codec losses, checkpoints and the training CLI (a short real run on the BEAT2 clip is slow-marked)."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from ecas.core.config import ConfigError
from ecas.core.paths import data_root
from gesture.body.motion import integrate_velocity
from gesture.body.regions import motion_to_features
from gesture.body.rotation import axis_angle_to_matrix
from gesture.codec.checkpoint import load_codec
from gesture.codec.config import CodecTrainConfig
from gesture.codec.data import load_motion_splits
from gesture.codec.losses import RegionLoss, integrate_root, laplacian, log_map, log_speed_error, velocity
from gesture.codec.train import commitment_ramp, main

torch.set_num_threads(1)
CLIP = data_root() / "beat2" / "2_scott_0_1_1.npz"
TINY_YAML = {
    "codec": {
        "latent_dim": 32,
        "n_filters": 16,
        "dim_feedforward": 64,
        "codebook_size": 32,
        "codebook_dim": 8,
        "kmeans_iters": 3,
        "dropout": 0.0,
        "regions": {
            "upper": {"n_q": 2, "num_layers": 1, "num_heads": 2},
            "lower": {"n_q": 2, "num_layers": 1, "num_heads": 2},
            "face": {"n_q": 2, "num_layers": 1, "num_heads": 2},
        },
    },
    "train": {"batch_size": 2, "window_frames": 16, "lr": 1e-3, "steps": 4, "checkpoint_every": 2},
}


def test_laplacian_velocity_and_integration_known_values():
    t = torch.arange(10.0)
    x = (t**2)[None, :, None]  # (1, 10, 1)
    torch.testing.assert_close(laplacian(x), torch.full((1, 6, 1), 2.0))
    torch.testing.assert_close(velocity(x)[0, :3, 0], torch.tensor([1.0, 3.0, 5.0]))
    vel = np.random.default_rng(0).normal(size=(7, 3))
    expected = integrate_velocity(vel, np.zeros(3), 25.0)
    torch.testing.assert_close(integrate_root(torch.tensor(vel)[None])[0], torch.tensor(expected))


def test_log_map_matches_axis_angle_and_has_finite_gradients():
    aa = torch.tensor([[0.3, -0.2, 0.1], [0.0, 0.0, 0.0], [1.5, 0.5, -1.0]])
    torch.testing.assert_close(log_map(axis_angle_to_matrix(aa)), aa, atol=1e-5, rtol=0)
    eye = torch.eye(3, requires_grad=True)
    log_map(eye).sum().backward()
    assert torch.isfinite(eye.grad).all()


@pytest.mark.parametrize("region", ["upper", "lower", "face"])
def test_region_loss_vanishes_on_the_target_and_grows_with_error(region):
    rng = np.random.default_rng(0)
    features = [
        motion_to_features(
            0.3 * rng.normal(size=(12, 55, 3)), 0.05 * rng.normal(size=(12, 3)).cumsum(0), rng.normal(size=(12, 100))
        )[region]
        for _ in range(2)
    ]
    target = torch.from_numpy(np.stack(features))  # (2, 12, nfeats)
    loss = RegionLoss(region)
    same = loss(target, target)
    for name in ("rot6d", "axis_angle", "rotmat_velocity", "joints", "contacts", "root_velocity", "expressions_l1"):
        if name in same:
            assert float(same[name]) < 1e-6, name
    torch.manual_seed(0)
    small = loss(target + 0.01 * torch.randn_like(target), target)["total"]
    large = loss(target + 0.3 * torch.randn_like(target), target)["total"]
    assert float(large) > float(small) > float(same["total"])
    with pytest.raises(ValueError, match="differ"):
        loss(target[:, :4], target)


def test_log_speed_error_sees_wobble_during_a_hold_that_velocity_mse_misses():
    hold = torch.zeros(1, 50, 1, 3)  # (B, T, J, 3): a joint at rest
    wobble = hold.clone()
    wobble[:, :, 0, 0] = 0.0005 * torch.sin(torch.arange(50.0))  # 0.5 mm: about 12 mm/s at 25 fps
    stroke = 0.01 * torch.arange(50.0)[None, :, None, None].expand(1, 50, 1, 3)  # 0.43 m/s
    assert float(log_speed_error(hold, hold, 0.005)) == 0.0
    assert float(log_speed_error(wobble, hold, 0.005)) > 0.1
    # the same wobble on top of a stroke barely changes its log speed
    assert float(log_speed_error(stroke + wobble, stroke, 0.005)) < 0.01 * float(log_speed_error(wobble, hold, 0.005))
    assert float(velocity(wobble).pow(2).mean()) < 1e-6  # what a position-velocity MSE sees


@pytest.mark.parametrize("region", ["upper", "lower"])
def test_log_speed_term_only_when_weighted(region):
    rng = np.random.default_rng(1)
    target = torch.from_numpy(
        motion_to_features(0.3 * rng.normal(size=(12, 55, 3)), np.zeros((12, 3)), rng.normal(size=(12, 100)))[region]
    )[None]  # (1, 12, nfeats)
    pred = target + 0.01 * torch.randn_like(target)
    assert "log_speed" not in RegionLoss(region)(pred, target)
    weighted = RegionLoss(region, log_speed_weight=0.5)(pred, target)
    assert float(weighted["log_speed"]) > 0
    assert float(weighted["total"]) > float(RegionLoss(region)(pred, target)["total"])


def test_expression_mse_punishes_a_missed_blink_more_than_l1_does():
    rest = torch.zeros(1, 50, 106)  # (B, T, face feats): jaw 6D + 100 expressions, all at rest
    blinks = rest.clone()
    blinks[:, ::10, 6:12] = 1.5  # a rare, large event on a few coefficients
    plain, weighted = RegionLoss("face"), RegionLoss("face", expression_mse_weight=20.0)
    assert "expressions_mse" not in plain(rest, blinks)
    missed = weighted(rest, blinks)  # predicting rest: the median, which L1 prefers
    assert float(missed["expressions_mse"]) > 4 * float(missed["expressions_l1"])


def test_joint_position_weight_scales_only_the_position_term():
    rng = np.random.default_rng(1)
    target = torch.from_numpy(
        motion_to_features(0.3 * rng.normal(size=(12, 55, 3)), np.zeros((12, 3)), rng.normal(size=(12, 100)))["upper"]
    )[None]  # (1, 12, 258)
    pred = target + 0.01 * torch.randn_like(target)
    reference, heavy = RegionLoss("upper")(pred, target), RegionLoss("upper", joint_position_weight=100.0)(pred, target)
    assert float(heavy["joints"]) == pytest.approx(10 * float(reference["joints"]), rel=1e-5)
    assert float(heavy["geodesic"]) == pytest.approx(float(reference["geodesic"]))


def test_negative_loss_weights_are_config_errors():
    for name in ("log_speed_weight", "expression_mse_weight", "joint_position_weight"):
        with pytest.raises(ConfigError, match=f"train.{name}: must be >= 0"):
            CodecTrainConfig(**{name: -1.0})


def test_commitment_ramp():
    assert [commitment_ramp(s, 4) for s in (0, 2, 4, 9)] == [0.0, 0.5, 1.0, 1.0]


@pytest.mark.skipif(not CLIP.is_file(), reason="needs ../shared/data/beat2")
def test_cli_trains_checkpoints_and_resumes(tmp_path, capsys):
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY_YAML))
    out = tmp_path / "run"
    assert main(["--config", str(config), "--region", "face", "--data", str(CLIP), "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["last"]["step"] == 4 and "jaw_error_deg" in report["last"]["heldout"]
    for name in ("model.safetensors", "config.yaml", "optimizer.safetensors", "trainer_state.json", "loss_curve.png"):
        assert (out / name).is_file(), name
    codec = load_codec(out)
    assert not codec.training and codec.nfeats == 106
    assert (
        main(
            [
                "--config",
                str(config),
                "--region",
                "face",
                "--data",
                str(CLIP),
                "--out",
                str(out),
                "--resume",
                "--steps",
                "6",
            ]
        )
        == 0
    )
    state = json.loads((out / "trainer_state.json").read_text())
    assert state["step"] == 6 and len(state["history"]["loss"]) == 6


@pytest.mark.slow
@pytest.mark.skipif(not CLIP.is_file(), reason="needs ../shared/data/beat2")
def test_short_training_run_lowers_mpjpe_on_the_clip_and_held_out(tmp_path, capsys):
    config = yaml.safe_load((Path(__file__).resolve().parents[1] / "ecas/configs/codec/small.yaml").read_text())
    config["train"].update(steps=150, checkpoint_every=150)
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(config))
    main(["--config", str(path), "--region", "upper", "--data", str(CLIP), "--out", str(tmp_path / "run")])
    report = json.loads(capsys.readouterr().out)
    for split in ("train", "heldout"):
        assert report["last"][split]["mpjpe_mm"] < 0.6 * report["first"][split]["mpjpe_mm"], split


@pytest.mark.skipif(not CLIP.is_file(), reason="needs ../shared/data/beat2")
def test_training_data_from_a_chunk_cache(tmp_path):
    from gesture.data.beat2 import find_takes
    from gesture.data.cache import build_cache
    from gesture.data.config import DataConfig

    build_cache(find_takes(CLIP.parent), DataConfig(), tmp_path / "cache")
    train, heldout = load_motion_splits(tmp_path / "cache", holdout_seconds=10.0)
    assert [s.num_frames for s in train] == [250] * 6 and heldout == []  # the clip is a train take
    assert train[0].features["lower"].shape == (250, 61) and train[0].poses.shape == (250, 55, 3)


def test_missing_data_is_a_clear_error(tmp_path):

    with pytest.raises(FileNotFoundError, match="neither a BEAT2 motion npz nor a chunk cache"):
        load_motion_splits(tmp_path / "nothing.npz", 10.0)
