"""The MIBURI release converter on random checkpoints written in the reference layout at reduced sizes."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

from ecas.core.body import REGIONS
from ecas.core.config import ConfigError
from ecas.core.spec import ConditionSpec
from gesture.codec.checkpoint import load_codec
from gesture.lm.checkpoint import load_lm
from gesture.nn.attention import StreamingMultiheadAttention
from gesture.process import build_generator
from gesture.release.convert import convert_release, main, release_gesture_config
from gesture.release.source import ReleaseError
from gesture.release.speakers import resolve_character, resolve_character_for_checkpoint
from gesture.release.synthetic import ReferenceSizes, codec_layout, glm_layout, write_experiment

torch.set_num_threads(1)
KEYS_DIR = Path(__file__).resolve().parents[2] / "shared" / "reference" / "state_dict_keys"
TINY = ReferenceSizes(
    latent=16,
    n_filters=8,
    codec_ffn=32,
    codec_layers=2,
    codec_heads=2,
    n_q={"upper": 3, "lower": 2, "face": 2},
    card=16,
    code_dim=4,
    d=32,
    temporal_layers=2,
    temporal_heads=2,
    depth_layers=3,
    depth_heads=1,
    ffn_hidden=48,
    n_speakers=9,
    text_vocab=50,
    audio_card=17,
    embed_dim=24,
)
STEP = 1920


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    root = tmp_path_factory.mktemp("miburi")
    files = write_experiment(root / "exp", TINY, seed=1)
    report = convert_release(root / "exp", root / "out", character="Wayne")
    return files, root / "out", report


def _source(path: Path) -> dict[str, torch.Tensor]:
    """The raw source tensors, prefix stripped, as fp32 (computed here independently of the converter)."""
    tensors = load_file(str(path))
    return {k.removeprefix("module."): v.float() for k, v in tensors.items()}


def _read_tsv(name: str) -> dict[str, tuple]:
    rows = (line.split("\t") for line in (KEYS_DIR / f"{name}.tsv").read_text().splitlines())
    return {k: tuple(int(x) for x in shape.strip("()").split(",") if x.strip()) for k, shape in rows}


@pytest.mark.skipif(not KEYS_DIR.exists(), reason="reference key lists not available")
def test_synthetic_layout_is_the_official_key_list_at_reference_sizes():
    sizes = ReferenceSizes()
    for region in REGIONS:
        assert codec_layout(sizes, region) == _read_tsv(f"codec_{region}")
    assert glm_layout(sizes, face_va=False) == _read_tsv("glm_vfl0")
    assert glm_layout(sizes, face_va=True) == _read_tsv("glm_vfl1")


def test_sizes_come_from_shapes_and_config(release):
    _, out, report = release
    lm = load_lm(out / "lm")
    s = lm.sizes
    assert (s.d_model, s.temporal_layers, s.temporal_heads, s.depth_layers, s.depth_heads, s.ffn_hidden) == (
        32,
        2,
        2,
        3,
        1,
        48,
    )
    assert (s.n_upper, s.n_lower, s.n_face, s.card, s.code_dim, s.n_speakers) == (3, 2, 2, 16, 4, 9)
    assert s.va_head and not s.va_use_face_logits
    assert lm.spec == ConditionSpec(name="moshi", text_vocab=50, audio_card=17, embed_dim=24)
    for region in REGIONS:
        codec = load_codec(out / "codecs" / region)
        layers = len(codec.transformer_encoder.transformer.layers)
        heads = codec.transformer_encoder.transformer.layers[0].self_attn.num_heads
        assert (codec.n_q, layers, heads) == ((2, 1, 1) if region == "face" else (TINY.n_q[region], 2, 2))
    assert report["glm"]["ignored_keys"] == {} and report["default_speaker"] == 6
    assert report["glm"]["stored_dtypes"] == ["torch.bfloat16"]
    assert json.loads((out / "release.json").read_text())["speakers"]["wayne"] == 6


def _independent_fold(g: np.ndarray, v: np.ndarray) -> np.ndarray:
    norm = np.sqrt((v.astype(np.float64) ** 2).sum(axis=tuple(range(1, v.ndim)), keepdims=True))
    return g * v / norm


def test_folded_weights_equal_g_v_over_norm(release):
    files, out, _ = release
    for region in REGIONS:
        source = {k: v.numpy() for k, v in _source(files.codecs[region]).items()}
        codec = load_codec(out / "codecs" / region)
        convs = [(n, m) for n, m in codec.named_modules() if getattr(m, "weight_norm", False)]
        assert len(convs) == sum(k.endswith("weight_g") for k in source) == 2 * (3 + 2 * TINY.residual_layers)
        for name, module in convs:
            expected = _independent_fold(source[f"{name}.weight_g"], source[f"{name}.weight_v"])
            np.testing.assert_allclose(module.folded_weight().detach().numpy(), expected, rtol=1e-5, atol=1e-7)
        # the transposed conv: v (C_in, C_out, K) and g (C_in, 1, 1), normalised per *input* channel
        key = "seanet_decoder.model.2.convtr.convtr"
        g, v = source[f"{key}.weight_g"], source[f"{key}.weight_v"]
        assert g.shape == (2 * TINY.n_filters, 1, 1) and v.shape == (2 * TINY.n_filters, TINY.n_filters, 4)
        per_input = _independent_fold(g, v)
        per_output = g * v / np.sqrt((v**2).sum(axis=(0, 2), keepdims=True))
        assert not np.allclose(per_input, per_output, rtol=1e-3)
        x = torch.randn(1, v.shape[0], 3)
        module = codec.seanet_decoder.model[2].convtr.convtr
        with torch.no_grad():
            ours = module(x)
        reference = F.conv_transpose1d(
            x, torch.from_numpy(per_input).float(), torch.from_numpy(source[f"{key}.bias"]), stride=2
        )
        torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-6)


def test_packed_qkv_split_heads_contiguous(release):
    files, out, _ = release
    source = _source(files.codecs["upper"])
    packed = source["transformer_encoder.transformer.layers.1.self_attn.in_projs.0.weight"].double()  # (3E, E)
    out_proj = source["transformer_encoder.transformer.layers.1.self_attn.out_projs.0.weight"].double()
    codec = load_codec(out / "codecs" / "upper")
    converted = codec.transformer_encoder.transformer.layers[1].self_attn
    e, heads, steps = TINY.latent, TINY.codec_heads, 6
    attention = StreamingMultiheadAttention(e, heads, context=25, rope=None)
    attention.load_state_dict(converted.state_dict())
    x = torch.randn(1, steps, e, dtype=torch.float64)
    with torch.no_grad():
        ours = attention.double()(x, torch.arange(steps))[0]
    wq, wk, wv = packed[:e], packed[e : 2 * e], packed[2 * e :]
    dh = e // heads
    heads_out = []
    for h in range(heads):
        rows = slice(h * dh, (h + 1) * dh)
        q, k, v = x[0] @ wq[rows].T, x[0] @ wk[rows].T, x[0] @ wv[rows].T  # (T, Dh)
        scores = (q @ k.T) / dh**0.5
        scores = scores.masked_fill(torch.ones(steps, steps).triu(1).bool(), float("-inf"))
        heads_out.append(scores.softmax(-1) @ v)
    expected = torch.cat(heads_out, dim=-1) @ out_proj.T
    torch.testing.assert_close(ours, expected, rtol=1e-9, atol=1e-9)


def test_codebooks_are_embedding_sum_over_clamped_usage(release):
    files, out, _ = release
    lm = load_lm(out / "lm")
    level = 0
    for region in REGIONS:
        source = _source(files.codecs[region])
        codec = load_codec(out / "codecs" / region)
        for i, layer in enumerate(codec.quantizer.vq.layers):
            usage = source[f"quantizer.vq.layers.{i}._codebook.cluster_usage"].numpy()
            summed = source[f"quantizer.vq.layers.{i}._codebook.embedding_sum"].numpy()
            assert usage[0] == 0.0 and usage[1] < 1e-5  # the clamp matters for these codes
            expected = summed / np.maximum(usage, 1e-5)[:, None]
            np.testing.assert_allclose(layer._codebook.embedding.numpy(), expected, rtol=1e-6)
            glm_copy = lm.codebook_vectors(level).detach().numpy()  # stored in bf16 by the reference
            np.testing.assert_allclose(glm_copy, expected, rtol=2e-2, atol=2e-2 * np.abs(expected).max())
            level += 1


def _sentinel(index: int) -> float:
    """Distinct values that bf16 stores exactly: (1 + j/128) * 2^e."""
    return (1 + (index % 128) / 128) * 2.0 ** (index // 128 - 4)


def test_every_source_tensor_lands_in_its_parameter(tmp_path):
    assigned: dict[str, dict[str, float]] = {}

    def fill(name, tensors):
        assigned[name] = {}
        for key in sorted(tensors):
            value = _sentinel(sum(len(v) for v in assigned.values()))
            tensors[key] = torch.full_like(tensors[key], value)
            assigned[name][key] = value

    write_experiment(tmp_path / "exp", TINY, fill=fill, glm_prefix="m.")
    convert_release(tmp_path / "exp", tmp_path / "out", check=False)
    assert len({v for d in assigned.values() for v in d.values()}) == sum(len(d) for d in assigned.values())
    models = {"glm": load_lm(tmp_path / "out" / "lm")}
    models.update({f"codec_{r}": load_codec(tmp_path / "out" / "codecs" / r) for r in REGIONS})
    for name, values in assigned.items():
        state = models[name].state_dict()
        assert set(state) == set(values), name
        for key, value in values.items():
            assert state[key].dtype == torch.float32
            assert bool((state[key] == value).all()), f"{name} {key}"


def test_face_va_head_is_detected_and_dropped(tmp_path):
    write_experiment(tmp_path / "exp", TINY, face_va=True)
    report = convert_release(tmp_path / "exp", tmp_path / "out")
    ignored = report["glm"]["ignored_keys"]
    dropped = {"vad_face_proj.weight", "vad_face_proj.bias", "vad_predictor.0.weight", "vad_predictor.7.bias"}
    assert dropped <= set(ignored)
    assert all(k.startswith(("vad_face_proj.", "vad_predictor.")) for k in ignored)
    lm = load_lm(tmp_path / "out" / "lm")
    assert not lm.sizes.va_head and not hasattr(lm, "vad_face_proj") and not hasattr(lm, "vad_predictor")


def _corrupt(path: Path, change) -> None:
    tensors = load_file(str(path))
    change(tensors)
    save_file(tensors, str(path))


def _drop_glm_key(t):
    del t["module.depformer_in.2.weight"]


def _add_codec_key(t):
    t["quantizer.vq.layers.0._codebook.extra"] = torch.zeros(3)


def _reshape_codec_key(t):
    t["transformer_decoder.transformer.layers.0.linear2.weight"] = torch.zeros(16, 31)


@pytest.mark.parametrize(
    "target, change, expected",
    [
        ("glm", _drop_glm_key, "missing key 'depformer_in.2.weight'"),
        ("lower", _add_codec_key, "unexpected key 'quantizer.vq.layers.0._codebook.extra'"),
        (
            "face",
            _reshape_codec_key,
            "key 'transformer_decoder.transformer.layers.0.linear2.weight' has shape (16, 31), expected (16, 32)",
        ),
    ],
)
def test_bad_checkpoints_stop_with_one_error_naming_file_and_key(tmp_path, capsys, target, change, expected):
    files = write_experiment(tmp_path / "exp", TINY)
    path = files.glm if target == "glm" else files.codecs[target]
    _corrupt(path, change)
    with pytest.raises(ReleaseError) as error:
        convert_release(tmp_path / "exp", tmp_path / "out")
    assert str(error.value).startswith(f"{path}: {expected}")
    assert main(["--experiment-dir", str(tmp_path / "exp"), "--out", str(tmp_path / "out")]) == 2
    assert expected in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_mismatched_codecs_and_missing_config_fields_are_refused(tmp_path):
    write_experiment(tmp_path / "a", TINY, seed=1)
    write_experiment(tmp_path / "b", TINY, seed=2)
    with pytest.raises(ReleaseError, match="not the ones this GLM was trained with"):
        convert_release(tmp_path / "a", tmp_path / "out", codec_dir=tmp_path / "b" / "codecs")
    config = tmp_path / "a" / "config.yaml"
    config.write_text(config.read_text().replace("gestureformer_heads: 2\n", ""))
    with pytest.raises(ReleaseError, match=r"config.yaml: field 'gestureformer_heads' must be an integer"):
        convert_release(tmp_path / "a", tmp_path / "out")


def test_converted_release_runs_streaming_steps_with_idle_gate_and_character(release):
    files, out, _ = release
    speaker = resolve_character_for_checkpoint(out / "lm", "lawrence")
    assert speaker == 4
    generator = build_generator(release_gesture_config(out, speaker, dtype="float32"), seed=3)
    loud = 0.3 * np.sin(np.arange(STEP) / 7.0).astype(np.float32)
    steps = [
        generator.step(t, np.arange(8) % TINY.audio_card, loud if t < 4 else np.zeros(STEP, np.float32))
        for t in range(10)
    ]
    generator.close()
    assert [s.idle for s in steps] == [False] * 4 + [False, False] + [True] * 4  # 3-step window of agent audio
    for s in steps:
        assert s.tokens.shape == (7,) and s.tokens.min() >= 0 and s.tokens.max() < TINY.card
        assert s.poses.shape == (2, 55, 3) and np.isfinite(s.poses).all() and np.isfinite(s.trans).all()
        assert np.isfinite(s.va_prob)
    with (
        np.load(files.root / "tokens_idle_slices" / "idle_upper_tokens_slices.npz") as src,
        np.load(out / "idle" / "idle_upper_tokens_slices.npz") as ours,
    ):
        np.testing.assert_array_equal(src["0"], ours["0"])
    bf16 = build_generator(release_gesture_config(out, speaker), seed=3)  # the runtime's default step dtype
    assert np.isfinite(bf16.step(1, np.zeros(8), loud).poses).all()
    bf16.close()


def test_character_resolution_and_refusing_to_overwrite(release, tmp_path, capsys):
    files, out, _ = release
    speakers = json.loads((out / "lm" / "speakers.json").read_text())
    assert resolve_character("STEWART", speakers, 9) == 3 and resolve_character("8", speakers, 9) == 8
    with pytest.raises(ConfigError, match="unknown speaker 'nobody'; known: scott \\(2\\)"):
        resolve_character("nobody", speakers, 9)
    with pytest.raises(ConfigError, match="index 9 is outside"):
        resolve_character(9, speakers, 9)
    args = ["--experiment-dir", str(files.root), "--out", str(out), "--no-check"]
    assert main(args) == 2 and "pass --force" in capsys.readouterr().err
    assert main([*args, "--force", "--character", "nobody"]) == 2
    assert (out / "release.json").is_file()  # a failed conversion leaves the previous one in place
