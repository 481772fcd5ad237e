"""The gesture LM model: checkpoint names, embeddings, conditioning tables, causality, masks, errors."""

from pathlib import Path

import pytest
import torch

from ecas.core.config import ConfigError
from ecas.core.spec import MOSHI_SPEC, ConditionSpec, SpecMismatchError
from gesture.lm.checkpoint import load_lm, save_lm
from gesture.lm.config import LMConfig
from gesture.lm.model import GestureLM, shift_history
from gesture.lm.stepper import LMStepper
from tests.lm_fixtures import TINY_SPEC, tiny_lm

torch.set_num_threads(1)
KEYS_DIR = Path(__file__).resolve().parents[2] / "shared" / "reference" / "state_dict_keys"


def _inputs(model: GestureLM, steps: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    s, spec = model.sizes, model.spec
    tokens = torch.randint(0, s.card, (2, s.n_levels, steps), generator=g)
    text = torch.randint(-1, spec.text_vocab, (2, steps), generator=g)
    audio = torch.randint(-1, spec.audio_card, (2, spec.n_audio_codebooks, steps), generator=g)
    return tokens, text, audio, torch.tensor([1, 3])


def _read_tsv(name: str) -> dict[str, tuple]:
    rows = (line.rstrip("\n").split("\t") for line in (KEYS_DIR / f"{name}.tsv").read_text().splitlines())
    return {k: tuple(int(x) for x in shape.strip("()").split(",") if x.strip()) for k, shape in rows}


@pytest.mark.skipif(not KEYS_DIR.exists(), reason="reference key lists not available")
@pytest.mark.parametrize("face_logits, tsv", [(False, "glm_vfl0"), (True, "glm_vfl1")])
def test_reference_size_state_dict_matches_official_keys(face_logits, tsv):
    small_spec = ConditionSpec(name="s", text_vocab=7, audio_card=5, embed_dim=MOSHI_SPEC.embed_dim)
    with torch.device("meta"):  # shapes only, no memory
        model = GestureLM(LMConfig(va_use_face_logits=face_logits), small_spec)
    ours = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    ref = _read_tsv(tsv)
    assert set(ours) == set(ref)
    vocab_dependent = {
        "text_procemb.weight": (32001, 4096),
        **{f"audio_procemb.{i}.weight": (2049, 4096) for i in range(8)},
    }
    for key, shape in ref.items():
        if key in vocab_dependent:
            assert shape == vocab_dependent[key]
        else:
            assert ours[key] == shape, key


def test_gesture_embedding_empty_is_zero_and_pad_is_learned():
    model = tiny_lm()
    emb = model.temporal_gemb[0]
    out = emb(torch.tensor([-1, 3, model.sizes.pad_token]))
    assert torch.equal(out[0], torch.zeros_like(out[0]))
    assert torch.equal(out[1], emb.weight[3])
    assert torch.equal(out[2], emb.pad_embedding.weight[0])


def test_projected_condition_tables_equal_lookup_then_linear():
    model = tiny_lm()
    stepper = LMStepper(model, guided=False)
    d = model.sizes.d_model
    for text, audio in (
        (5, torch.tensor([0, 1, 2, 3, 4, 5, 6, 11])),
        (-1, torch.tensor([-1, 2, -1, 3, 0, -1, 1, 1])),
        (-1, torch.full((8,), -1)),
    ):
        audio_sum, text_emb = model.condition_embeddings(torch.tensor([[text]]), audio.view(1, 8, 1))
        memories = stepper.condition_memories(text, audio)  # (2, 2d)
        with torch.no_grad():
            for proj, cols in ((model.temp_condproj, slice(0, d)), (model.dep_condproj, slice(d, 2 * d))):
                torch.testing.assert_close(memories[0, cols], proj[0](audio_sum)[0, 0], atol=1e-5, rtol=1e-5)
                torch.testing.assert_close(memories[1, cols], proj[1](text_emb)[0, 0], atol=1e-5, rtol=1e-5)


def test_full_forward_is_causal_in_the_condition_and_history():
    model = tiny_lm()
    tokens, text, audio, spk = _inputs(model, 20)
    with torch.no_grad():
        ref = model(tokens, text, audio, spk).logits
        t = 11
        text2, audio2, tokens2 = text.clone(), audio.clone(), tokens.clone()
        text2[:, t:] = (text2[:, t:] + 7) % model.spec.text_vocab
        audio2[:, :, t:] = (audio2[:, :, t:] + 3) % model.spec.audio_card
        tokens2[:, :, t:] = (tokens2[:, :, t:] + 1) % model.sizes.card  # step t's tokens feed steps > t only
        out = model(tokens2, text2, audio2, spk).logits
    assert torch.equal(out[:, :t], ref[:, :t])
    assert not torch.allclose(out[:, t:], ref[:, t:])


def test_depth_is_causal_over_levels():
    model = tiny_lm()
    tokens, text, audio, spk = _inputs(model, 4)
    with torch.no_grad():
        ref = model(tokens, text, audio, spk).logits
        changed = tokens.clone()
        changed[:, 5] = (changed[:, 5] + 1) % model.sizes.card  # level 5 is an input of depth position 5
        out = model(changed, text, audio, spk, history=shift_history(tokens)).logits
    assert torch.equal(out[:, :, :6], ref[:, :, :6])
    assert not torch.allclose(out[:, :, 6:], ref[:, :, 6:])


def test_lower_body_depth_rows_get_zero_cross_attention():
    model = tiny_lm()
    layer = model.depth_transformer.layers[0]
    masked = model.cross_masked
    assert masked.tolist() == [k + 1 in model.sizes.lower_levels for k in range(model.sizes.n_depth)]
    query = torch.randn(3, model.sizes.n_depth, model.sizes.d_model)
    memory = torch.randn(3, 1, model.sizes.d_model)
    with torch.no_grad():
        out = layer._cross(layer.cross_attns[0], query, memory, masked)
    assert torch.equal(out[:, masked], torch.zeros_like(out[:, masked]))
    assert (out[:, ~masked].abs() > 0).all(dim=-1).all()


def test_out_of_range_tokens_raise_clear_errors():
    model = tiny_lm()
    tokens, text, audio, spk = _inputs(model, 3)
    bad_text = text.clone()
    bad_text[0, 0] = model.spec.text_vocab
    with pytest.raises(ValueError, match="text tokens"):
        model(tokens, bad_text, audio, spk)
    with pytest.raises(ValueError, match="audio codes"):
        model(tokens, text, audio[:, :7], spk)


def test_checkpoint_round_trip_and_spec_mismatch(tmp_path):
    model = tiny_lm()
    save_lm(model, tmp_path, epoch=3)
    loaded = load_lm(tmp_path, TINY_SPEC)
    loaded_state = loaded.state_dict()
    for key, value in model.state_dict().items():
        assert torch.equal(loaded_state[key], value), key
    with pytest.raises(SpecMismatchError, match="condition spec"):
        load_lm(tmp_path, MOSHI_SPEC)


def test_lm_config_rejects_bad_sizes():
    with pytest.raises(ConfigError, match="lm.temporal_heads"):
        LMConfig(d_model=30, temporal_heads=4)
    with pytest.raises(ConfigError, match="lm.n_upper"):
        LMConfig(n_upper=0)
