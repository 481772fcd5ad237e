"""FGD encoders: the BEAT2 VAESKConv encoder (topology, same-format checkpoint) and its use in evaluate."""

import json

import numpy as np
import pytest
import torch

from gesture.data.errors import DataError
from gesture.evaluate import main as evaluate_main
from gesture.fgd import frechet_distance
from gesture.fgd_vaeskconv import (
    VAESKConvEncoder,
    edge_neighbours,
    edge_topology,
    load_vaeskconv_encoder,
    skeleton_chains,
)
from gesture.skeleton import PARENTS
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
