"""The moshi backend end to end with a tiny random Moshi + Mimi saved in the released file formats."""

import json

import numpy as np
import pytest
import torch

pytest.importorskip("moshi")
pytest.importorskip("sentencepiece")

from dialogue.config import DialogueConfig
from dialogue.moshi_backend import MoshiWeightsError, moshi_spec
from dialogue.process import create_component
from ecas.core.component import RunContext
from ecas.core.config import build_dataclass
from ecas.core.messages import AudioUser, DialogueStep
from ecas.core.spec import MOSHI_SPEC
from ecas.core.timing import STEP_SAMPLES

TINY_CARD = 64
TINY_TEXT_CARD = 64
TINY_MIMI = {
    "sample_rate": 24000,
    "channels": 1,
    "frame_rate": 12.5,
    "seanet": {
        "channels": 1,
        "dimension": 32,
        "causal": True,
        "n_filters": 4,
        "n_residual_layers": 1,
        "activation": "ELU",
        "compress": 2,
        "dilation_base": 2,
        "disable_norm_outer_blocks": 0,
        "kernel_size": 7,
        "residual_kernel_size": 3,
        "last_kernel_size": 3,
        "norm": "none",
        "pad_mode": "constant",
        "ratios": [8, 6, 5, 4],
        "true_skip": True,
    },
    "quantizer": {"dimension": 16, "n_q": 8, "bins": TINY_CARD, "input_dimension": 32, "output_dimension": 32},
    "transformer": {
        "d_model": 32,
        "num_heads": 2,
        "num_layers": 1,
        "causal": True,
        "layer_scale": 0.01,
        "context": 25,
        "conv_layout": True,
        "max_period": 10000,
        "gating": "none",
        "norm": "layer_norm",
        "positional_embedding": "rope",
        "dim_feedforward": 64,
        "input_dimension": 32,
        "output_dimensions": [32],
    },
}
TINY_LM = {
    "dim": 32,
    "text_card": TINY_TEXT_CARD,
    "existing_text_padding_id": 3,
    "n_q": 16,
    "dep_q": 8,
    "card": TINY_CARD,
    "num_heads": 2,
    "num_layers": 1,
    "hidden_scale": 2.0,
    "causal": True,
    "layer_scale": None,
    "context": 50,
    "max_period": 10000,
    "gating": "silu",
    "norm": "rms_norm_f32",
    "positional_embedding": "rope",
    "depformer_dim": 32,
    "depformer_dim_feedforward": 64,
    "depformer_num_heads": 2,
    "depformer_num_layers": 1,
    "depformer_layer_scale": None,
    "depformer_multi_linear": True,
    "depformer_context": 8,
    "depformer_max_period": 10000,
    "depformer_gating": "silu",
    "depformer_pos_emb": "none",
    "depformer_weights_per_step": True,
    "delays": [0, 0, 1, 1, 1, 1, 1, 1, 1, 0, 1, 1, 1, 1, 1, 1, 1],
}


@pytest.fixture(scope="module")
def tiny_moshi_files(tmp_path_factory):
    """Random tiny Mimi + LM saved as safetensors, their config jsons, and a sentencepiece model trained here."""
    import sentencepiece
    from moshi.models import loaders
    from safetensors.torch import save_file

    root = tmp_path_factory.mktemp("moshi")
    torch.manual_seed(0)
    mimi = loaders.get_mimi(None, TINY_MIMI)
    lm = loaders.get_moshi_lm(None, TINY_LM, dtype=torch.float32)
    save_file({k: v.contiguous() for k, v in mimi.state_dict().items()}, str(root / "mimi.safetensors"))
    save_file({k: v.contiguous() for k, v in lm.state_dict().items()}, str(root / "model.safetensors"))
    (root / "mimi.json").write_text(json.dumps(TINY_MIMI))
    (root / "lm.json").write_text(json.dumps(TINY_LM))
    corpus = root / "corpus.txt"
    corpus.write_text(
        "\n".join(
            [
                "hello there how are you today",
                "i am fine thank you very much",
                "the weather is nice and warm",
                "what would you like to talk about",
            ]
            * 20
        )
    )
    sentencepiece.SentencePieceTrainer.train(
        input=str(corpus),
        model_prefix=str(root / "spm"),
        vocab_size=TINY_TEXT_CARD,
        model_type="unigram",
        hard_vocab_limit=False,
        minloglevel=2,
    )
    return root


def _moshi_cfg(root, **overrides) -> DialogueConfig:
    moshi = {
        "lm_weights": str(root / "model.safetensors"),
        "mimi_weights": str(root / "mimi.safetensors"),
        "tokenizer": str(root / "spm.model"),
        "lm_config": str(root / "lm.json"),
        "mimi_config": str(root / "mimi.json"),
        "temp": 0.8,
        "temp_text": 0.7,
    }
    moshi.update(overrides)
    return build_dataclass(DialogueConfig, {"backend": "moshi", "moshi": moshi}, "dialogue")


def test_tiny_moshi_runs_through_the_dialogue_component(tiny_moshi_files, tmp_path):
    component = create_component(_moshi_cfg(tiny_moshi_files), RunContext(tmp_path, False, 0, "s"))
    assert component.spec == moshi_spec(component.backend.lm)
    assert component.spec.text_vocab == TINY_TEXT_CARD + 1 and component.spec.audio_card == TINY_CARD + 1
    rng = np.random.default_rng(0)
    steps = []
    for i in range(8):
        pcm = (0.1 * rng.standard_normal(STEP_SAMPLES)).astype(np.float32)
        (out,) = component.handle(AudioUser(pcm=pcm, step=i))
        assert isinstance(out, DialogueStep)
        steps.append(out)
    component.close()
    max_delay = max(TINY_LM["delays"])
    for out in steps[:max_delay]:  # LMGen's warm-up: nothing generated yet
        assert out.text_token == -1 and (out.agent_codes == -1).all()
    for out in steps[max_delay:]:
        assert 0 <= out.text_token < TINY_TEXT_CARD + 1
        assert ((out.agent_codes >= 0) & (out.agent_codes < TINY_CARD)).all()
        assert out.agent_pcm.shape == (STEP_SAMPLES,) and np.isfinite(out.agent_pcm).all()
    for out in steps:
        assert ((out.user_codes >= 0) & (out.user_codes < TINY_CARD)).all()
    assert any(np.abs(out.agent_pcm).max() > 0 for out in steps[max_delay:])
    transcript = json.loads((tmp_path / "transcript.json").read_text())
    assert transcript["backend"] == "moshi"


def test_classifier_free_guidance_from_config(tiny_moshi_files, tmp_path):
    component = create_component(
        _moshi_cfg(tiny_moshi_files, cfg_coef=2.0, temp=0.0, temp_text=0.0), RunContext(tmp_path, False, 0, "s")
    )
    assert component.backend.lm_gen.cfg_coef == 2.0 and component.backend.lm_gen.temp == 0.0
    outs = [component.handle(AudioUser(pcm=np.zeros(STEP_SAMPLES, np.float32), step=i))[0] for i in range(4)]
    component.close()
    assert all(0 <= o.text_token < TINY_TEXT_CARD + 1 for o in outs[1:])
    assert all(((o.agent_codes >= 0) & (o.agent_codes < TINY_CARD)).all() for o in outs[1:])


def test_released_sizes_give_moshi_spec():
    from moshi.models import loaders

    class Sizes:  # the released 7B's sizes, without building it
        text_card, card, dim = loaders._lm_kwargs["text_card"], loaders._lm_kwargs["card"], loaders._lm_kwargs["dim"]

    assert moshi_spec(Sizes) == MOSHI_SPEC


def test_missing_weights_name_the_expected_files(tmp_path):
    cfg = build_dataclass(
        DialogueConfig, {"backend": "moshi", "moshi": {"lm_weights": str(tmp_path / "nope")}}, "dialogue"
    )
    with pytest.raises(MoshiWeightsError) as err:
        create_component(cfg, RunContext(tmp_path, False, 0, "s"))
    message = str(err.value)
    for expected in (
        "model.safetensors",
        "tokenizer-e351c8d8-checkpoint125.safetensors",
        "tokenizer_spm_32k_3.model",
        "dialogue.moshi.lm_weights",
        "dialogue.moshi.mimi_weights",
        "dialogue.moshi.tokenizer",
    ):
        assert expected in message
