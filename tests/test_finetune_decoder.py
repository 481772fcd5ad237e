"""`ecas train-codec --finetune-decoder DIR`: only the decoder half learns, so the codes stay fixed."""

import pytest
import torch
import yaml
from safetensors.torch import load_file

from gesture.codec.checkpoint import MODEL_FILE, load_codec
from gesture.codec.data import load_motion_splits, sample_batch
from gesture.codec.train import main
from tests.test_codec_training import CLIP, TINY_YAML

torch.set_num_threads(1)
DECODER_HALF = ("transformer_decoder.", "seanet_decoder.")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("finetune")
    config = root / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY_YAML))
    base, tuned = root / "base", root / "tuned"
    common = ["--config", str(config), "--region", "upper", "--data", str(CLIP)]
    assert main(common + ["--out", str(base)]) == 0
    assert main(common + ["--out", str(tuned), "--steps", "6", "--finetune-decoder", str(base)]) == 0
    return base, tuned


def test_only_the_decoder_half_changes(trained):
    base, tuned = (load_file(str(d / MODEL_FILE)) for d in trained)
    changed = {k for k in base if not torch.equal(base[k], tuned[k])}
    assert changed, "the decoder did not learn"
    assert all(k.startswith(DECODER_HALF) for k in changed), sorted(changed)
    assert any(k.startswith("seanet_decoder.") for k in changed) and any(
        k.startswith("transformer_decoder.") for k in changed
    )


def test_codes_of_real_motion_are_unchanged(trained):
    base, tuned = (load_codec(d) for d in trained)
    clips, _ = load_motion_splits(CLIP, 10.0)
    frames = sample_batch(clips, "upper", 2, 32, 0.0, torch.Generator().manual_seed(0))  # (2, 32, nfeats)
    with torch.no_grad():
        assert torch.equal(base.encode(frames), tuned.encode(frames))
        assert not torch.equal(base.decode(base.encode(frames)), tuned.decode(tuned.encode(frames)))


@pytest.mark.parametrize("option", ["--finetune-decoder", "--init-from"])
def test_a_missing_trained_codec_is_a_clear_error(tmp_path, capsys, option):
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY_YAML))
    nowhere = tmp_path / "nowhere"
    code = main(
        [
            "--config",
            str(config),
            "--region",
            "upper",
            "--data",
            str(CLIP),
            "--out",
            str(tmp_path / "o"),
            option,
            str(nowhere),
        ]
    )
    assert code == 2
    assert capsys.readouterr().err.strip() == f"error: {option} {nowhere}: no checkpoint there"
