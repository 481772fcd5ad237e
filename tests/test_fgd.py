"""FGD encoders: the BEAT2 VAESKConv encoder (topology, same-format checkpoint) and its use in evaluate."""

import json

import numpy as np
import pytest
import torch

from ecas.core.errors import DataError
from gesture.body.skeleton import PARENTS
from gesture.eval.evaluate import main as evaluate_main
from gesture.eval.fgd import frechet_distance
from gesture.eval.fgd_vaeskconv import (
    VAESKConvEncoder,
    edge_neighbours,
    edge_topology,
    load_vaeskconv_encoder,
    skeleton_chains,
)
from tests.data.beat2_clip import CLIP_NPZ, needs_clip

torch.set_num_threads(1)


def test_topology_gives_the_reference_sizes():
    edges = edge_topology(PARENTS)
    assert len(edges) == 55 and edges[0] == (0, 55) and edges[20] == (18, 20)
    near = edge_neighbours(edges, 2)
    # wrist edge: itself, the forearm and upper arm, and the first two bones of every finger
    assert sorted(near[20]) == [16, 18, 20, 25, 26, 28, 29, 31, 32, 34, 35, 37, 38]
    chains = skeleton_chains(edges)
    assert len(chains) == 20 and chains[:3] == [[0], [1, 4, 7, 10], [2, 5, 8, 11]]
    enc = VAESKConvEncoder()
    assert [len(layer[0].groups) for layer in enc.layers] == [35, 20, 20, 20]
    assert enc.latent_dim == 240  # 20 chains x 12 channels: "latent 240, input 330"
    assert enc.layers[0][0].residual[0].weight.shape == (330, 330, 4)
    out = enc(torch.randn(2, 64, 330))
    assert out.shape == (2, 4, 240)


def _same_format_checkpoint(path, seed=0):
    """A file laid out like BEAT2's AESKConv_240_100.bin: torch.save({'model_state': ...}) of the whole VAE."""
    torch.manual_seed(seed)
    enc = VAESKConvEncoder()
    for p in enc.parameters():
        torch.nn.init.normal_(p, std=0.05)
    state = {f"module.encoder.{k}": v for k, v in enc.state_dict().items()}
    state["module.decoder.main.0.weight"] = torch.randn(240, 240, 3)  # the decoder half is ignored
    state["module.fc_mu.weight"] = torch.randn(240, 240)
    torch.save({"model_state": state, "epoch": 100}, path)
    return enc


def test_load_same_format_checkpoint(tmp_path):
    path = tmp_path / "AESKConv_240_100.bin"
    source = _same_format_checkpoint(path)
    loaded = load_vaeskconv_encoder(path)
    x = torch.randn(1, 96, 330)
    torch.testing.assert_close(loaded(x), source(x))
    poses = np.random.default_rng(0).normal(size=(100, 55, 3)).astype(np.float32) * 0.3
    feats = loaded.features(poses, None)
    assert feats.shape == (96 // 16, 240)  # trimmed to 96 frames, one latent per 16


def test_bad_checkpoints(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_vaeskconv_encoder(tmp_path / "none.bin")
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="cannot read"):
        load_vaeskconv_encoder(junk)
    torch.save({"model_state": {"decoder.x": torch.zeros(1)}}, junk)
    with pytest.raises(DataError, match="no 'encoder"):
        load_vaeskconv_encoder(junk)
    torch.save({"model_state": {"encoder.layers.0.0.shortcut.bias": torch.zeros(7)}}, junk)
    with pytest.raises(DataError, match="not a VAESKConv encoder"):
        load_vaeskconv_encoder(junk)


@needs_clip
def test_evaluate_with_learned_fgd(tmp_path, capsys):
    path = tmp_path / "AESKConv_240_100.bin"
    _same_format_checkpoint(path)
    code = evaluate_main(["--motion", str(CLIP_NPZ), "--gt", str(CLIP_NPZ), "--fgd-encoder", str(path), "--json"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["fgd_vaeskconv"] == pytest.approx(0.0, abs=1e-6)
    assert "beat_align" not in result  # no --wav


def test_frechet_of_encoder_features_separates_motions():
    enc = VAESKConvEncoder()
    rng = np.random.default_rng(1)
    calm = rng.normal(size=(640, 55, 3)).astype(np.float32) * 0.05
    wild = rng.normal(size=(640, 55, 3)).astype(np.float32) * 0.8
    same = frechet_distance(enc.features(calm, None), enc.features(calm.copy(), None))
    apart = frechet_distance(enc.features(calm, None), enc.features(wild, None))
    assert same == pytest.approx(0.0, abs=1e-6) and apart > 1e-3


@needs_clip
def test_kinetic_fgd_grows_with_noise_on_the_scale_of_real_differences():
    """GT against itself delayed 0.4 s, against its other half, frozen, and with growing rotation noise on the
    body joints: the noise's distances grow with it and stay between a delay's and a frozen body's."""
    from gesture.eval import metrics as M
    from gesture.eval.fgd import kinetic_fgd

    gt = M.load_motion_clip(CLIP_NPZ).at_fps(25)
    gt_joints = M.prepare_pair(gt, gt).gt_joints

    def joints_of(poses):
        clip = M.MotionClip(poses, gt.trans, gt.expressions, 25)
        return M.prepare_pair(clip, clip).gt_joints

    delayed = kinetic_fgd(joints_of(np.concatenate([np.repeat(gt.poses[:1], 10, 0), gt.poses[:-10]])), gt_joints)
    half = len(gt_joints) // 2
    halves = kinetic_fgd(gt_joints[:half], gt_joints[half:])
    frozen = kinetic_fgd(np.repeat(gt_joints[:1], len(gt_joints), 0), gt_joints)
    noise = []
    for sigma in (0.0025, 0.005, 0.01, 0.02):
        poses = gt.poses.reshape(len(gt.poses), -1).copy()
        poses[:, 3:66] += np.random.default_rng(0).normal(0, sigma, size=(len(poses), 63)).astype(np.float32)
        noise.append(kinetic_fgd(joints_of(poses.reshape(-1, 55, 3)), gt_joints))
    assert kinetic_fgd(gt_joints, gt_joints) == pytest.approx(0.0, abs=1e-6)
    assert delayed < 0.01 < halves < 1.0 < noise[0]
    assert all(a < b for a, b in zip(noise, noise[1:])) and noise[-1] < frozen < 100
