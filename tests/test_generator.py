"""The streaming gesture generator: shapes, determinism, reset, causality, CFG, pad, idle gate, translation."""

import numpy as np
import pytest
import torch

from gesture.body.regions import LOWER_VELOCITY_SLICE
from gesture.body.rotation import axis_angle_to_matrix
from gesture.generator import GestureGenerator
from gesture.layers.idle_gate import IdleGate
from tests.kernels import KERNELS, using
from tests.lm_fixtures import tiny_codecs, tiny_lm

torch.set_num_threads(1)


def _generator(**kwargs) -> GestureGenerator:
    return GestureGenerator(tiny_lm(), tiny_codecs(), **kwargs)


def _conditions(steps, seed=0):
    rng = np.random.default_rng(seed)
    return [(int(rng.integers(-1, 40)), rng.integers(-1, 12, 8)) for _ in range(steps)]


def _run(gen, conditions):
    return [gen.step(text, audio) for text, audio in conditions]


def test_step_outputs_shapes_and_types():
    gen = _generator()
    out = gen.step(3, np.arange(8))
    assert out.tokens.shape == (20,) and out.tokens.dtype == np.int32
    assert out.poses.shape == (2, 55, 3) and out.poses.dtype == np.float32
    assert out.trans.shape == (2, 3) and out.expressions.shape == (2, 100)
    assert 0.0 < out.va_prob < 1.0
    assert np.isfinite(out.poses).all() and np.all(out.poses[:, 23:25] == 0)  # eyes are not modelled
    assert ((out.tokens >= 0) & (out.tokens < 16)).all()


def test_same_seed_same_motion_and_reset_replays_the_session():
    conditions = _conditions(15)
    a = _run(_generator(seed=7), conditions)
    gen = _generator(seed=7)
    b = _run(gen, conditions)
    gen.reset()
    c = _run(gen, conditions)
    for x, y, z in zip(a, b, c):
        assert np.array_equal(x.tokens, y.tokens) and np.array_equal(x.tokens, z.tokens)
        assert np.array_equal(x.poses, y.poses) and np.array_equal(x.trans, z.trans)
    other = _run(_generator(seed=8), conditions)
    assert any(not np.array_equal(x.tokens, y.tokens) for x, y in zip(a, other))


def test_changing_the_condition_at_t_never_changes_earlier_steps():
    # the tiny random LM barely listens to its condition (~1e-4 in probability) and inverse-CDF draws move only
    # with the probabilities, so a strong guidance scale makes the later change visible in the tokens
    conditions = _conditions(20)
    ref = _run(_generator(seed=1, cfg_scale=300.0), conditions)
    t = 12
    changed = conditions[:t] + [((text + 5) % 40, (audio + 3) % 12) for text, audio in conditions[t:]]
    out = _run(_generator(seed=1, cfg_scale=300.0), changed)
    for i in range(t):
        assert np.array_equal(out[i].tokens, ref[i].tokens)
        assert np.array_equal(out[i].poses, ref[i].poses) and np.array_equal(out[i].expressions, ref[i].expressions)
    assert any(not np.array_equal(out[i].tokens, ref[i].tokens) for i in range(t, 20))


def test_pad_is_never_emitted_even_when_the_model_prefers_it():
    lm = tiny_lm()
    with torch.no_grad():
        lm.temporal_classifier.weight[lm.sizes.pad_token] *= 0
        lm.temporal_classifier.weight[lm.sizes.pad_token, :] += 10.0
        for classifier in lm.depformer_classifier:
            classifier.weight[lm.sizes.pad_token] = 10.0
    gen = GestureGenerator(lm, tiny_codecs())
    for out in _run(gen, _conditions(10)):
        assert (out.tokens != lm.sizes.pad_token).all()


def test_cfg_guides_every_level_but_the_lower_body():
    gen = _generator(cfg_scale=3.0)
    assert gen._guidance(0) == 3.0 and gen._guidance(gen.sizes.face_levels.start) == 3.0
    assert all(gen._guidance(level) == 1.0 for level in gen.sizes.lower_levels)
    logits = gen._sample(torch.zeros(17), 0)
    assert 0 <= logits < 16  # pad (16) masked


def test_hold_bias_repeats_the_previous_token_at_its_levels():
    conditions = _conditions(12)
    free = np.stack([out.tokens for out in _run(_generator(seed=3), conditions)])  # (T, K)
    held = np.stack([out.tokens for out in _run(_generator(seed=3, hold_bias=1e4, hold_levels=(1, 2)), conditions)])
    assert np.array_equal(held[0], free[0])  # no previous step: nothing to favour
    assert (held[1:, 1:3] == held[:1, 1:3]).all()  # held from then on
    assert not (free[1:, 1:3] == free[:1, 1:3]).all()


def test_translation_integrates_the_decoded_root_velocity():
    gen = _generator(initial_translation=(0.0, 1.3, 0.0))
    out = gen.step(1, np.zeros(8, int))
    assert np.allclose(out.trans[0], [0.0, 1.3, 0.0])
    tokens = torch.from_numpy(out.tokens.astype(np.int64))
    gen2 = _generator()
    lower = gen2.decoders["lower"].step(tokens[gen2.level_slices["lower"]].view(1, -1, 1))[0].numpy()
    velocity = lower[:, LOWER_VELOCITY_SLICE]
    assert np.allclose(out.trans[1], out.trans[0] + velocity[0] / 25, atol=1e-5)
    nxt = gen.step(1, np.zeros(8, int))
    assert np.allclose(nxt.trans[0], out.trans[1] + velocity[1] / 25, atol=1e-5)


def test_idle_gate_swaps_upper_and_face_tokens_while_silent():
    upper = np.arange(8 * 5).reshape(8, 5) % 16
    face = (np.arange(4 * 3).reshape(4, 3) + 1) % 16
    gate = IdleGate(upper, face, slice(0, 8), slice(16, 20), window_samples=100, l2_threshold=0.5, rewind_below=3)
    tokens = np.full(20, 9)
    silent = gate.apply(tokens)
    assert np.array_equal(silent[:8], upper[:, 0]) and np.array_equal(silent[16:], face[:, 0])
    assert np.array_equal(silent[8:16], tokens[8:16]) and np.array_equal(tokens, np.full(20, 9))
    gate.apply(tokens)
    gate.apply(tokens)  # upper cursor at 3 of 5, face cursor wrapped to 0
    gate.push_audio(np.full(1920, 0.3, np.float32))
    assert not gate.silent
    assert np.array_equal(gate.apply(tokens), tokens)
    assert gate.cursors["upper"].position == 0  # 2 tokens left < rewind_below 3: rewound
    gate.push_audio(np.zeros(1920, np.float32))
    assert gate.silent


def test_generator_with_idle_gate_keeps_its_own_history():
    gate = IdleGate(np.zeros((8, 4), int), np.zeros((4, 4), int), slice(0, 8), slice(16, 20))
    conditions = _conditions(6)
    gated = _generator(layers=[gate])
    plain = _run(_generator(), conditions)
    silence = np.zeros(1920, np.float32)
    for (text, audio), ref in zip(conditions, plain):
        out = gated.step(text, audio, silence)
        assert out.idle and np.array_equal(out.tokens, ref.tokens)  # the LM's tokens are unchanged


def test_bad_inputs_raise_clear_errors():
    gen = _generator()
    with pytest.raises(ValueError, match="audio_codes: expected 8"):
        gen.step(1, np.zeros(7, int))
    with pytest.raises(ValueError, match="text_token"):
        gen.step(40, np.zeros(8, int))
    with pytest.raises(ValueError, match="audio_codes: must be in"):
        gen.step(1, np.full(8, 12))
    with pytest.raises(ValueError, match="hold_levels"):
        _generator(hold_levels=(20,))
    codecs = tiny_codecs(card=32)
    with pytest.raises(ValueError, match="LM card"):
        GestureGenerator(tiny_lm(), codecs)


@pytest.mark.slow
@pytest.mark.timeout(4 * 3600)
def test_soak_memory_stays_flat():
    """45,000 steps (1 hour of motion) at the small size: the resident memory must not grow."""
    import os
    import resource

    from ecas.core.config import build_dataclass, load_yaml
    from gesture.codec.build import build_codec
    from gesture.codec.config import load_codec_config
    from gesture.lm.config import LMFileConfig
    from gesture.lm.model import GestureLM

    steps = int(os.environ.get("GESTURE_SOAK_STEPS", 45_000))
    cfg = build_dataclass(LMFileConfig, load_yaml("ecas/configs/lm/small.yaml"))
    lm = GestureLM(cfg.lm, cfg.condition).eval()
    codec_cfg = load_codec_config("ecas/configs/codec/small.yaml").codec
    gen = GestureGenerator(lm, {r: build_codec(codec_cfg, r).eval() for r in ("upper", "lower", "face")})
    rng = np.random.default_rng(0)

    def rss_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 2**20

    samples = []
    for i in range(steps):
        gen.step(int(rng.integers(-1, 8192)), rng.integers(-1, 256, 8), None)
        if i % 500 == 0:
            samples.append(rss_mb())
        if i % 5000 == 0:
            print(f"soak step {i}: RSS {samples[-1]:.1f} MB", flush=True)
    warm = samples[len(samples) // 10]
    print(
        f"soak: {steps} steps, RSS MB first {samples[0]:.1f}, after warm-up {warm:.1f}, last {samples[-1]:.1f}, "
        f"max {max(samples):.1f}"
    )
    assert max(samples[len(samples) // 10 :]) - warm < 20, samples


@pytest.mark.parametrize("kernels", KERNELS)
def test_bfloat16_step_path_decodes_close_to_float32(kernels):
    """bfloat16 LM weights pair with float16 codec weights; joint rotations within 0.02 rad (geodesic: axis-angle
    vectors jump near pi). int8's precision is tested per model (test_codec_inference, test_lm_stepper): random tiny
    codecs amplify it here."""
    dtype = "bfloat16"
    lm, codecs = tiny_lm(), tiny_codecs()
    first = GestureGenerator(lm, codecs)
    tokens = torch.from_numpy(first.step(1, np.arange(8)).tokens.astype(np.int64))
    first.close()  # the codecs stream for one generator at a time
    with using(kernels, dtype):
        fast = GestureGenerator(lm, codecs, dtype=dtype)
    exact = GestureGenerator(lm, codecs, dtype="float32")
    assert type(codecs["upper"].transformer_decoder.transformer.layers[0].linear1) is torch.nn.Linear  # not mutated
    for _ in range(3):
        (poses, *rest), (poses_ref, *rest_ref) = fast._decode(tokens), exact._decode(tokens)  # + trans, face, contacts
        assert _geodesic_rad(poses, poses_ref).max() < 0.02
        for x, y in zip(rest, rest_ref):
            assert np.abs(x - y).max() < 0.02 * max(1.0, np.abs(y).max())


def _geodesic_rad(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation between axis-angle rotations a and b (..., 3)."""
    relative = axis_angle_to_matrix(torch.from_numpy(a).double()).transpose(-1, -2) @ axis_angle_to_matrix(
        torch.from_numpy(b).double()
    )
    cosine = (relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.arccos(cosine.clamp(-1.0, 1.0)).numpy()


def test_idle_slices_load_from_the_reference_layout(tmp_path):
    from gesture.layers.idle_gate import load_idle_slices

    np.savez(tmp_path / "idle_upper_tokens_slices.npz", **{"0": np.arange(8 * 6).reshape(1, 8, 6) % 16})
    with pytest.raises(FileNotFoundError, match="idle_face_tokens_slices.npz"):
        load_idle_slices(tmp_path)
    np.savez(tmp_path / "idle_face_tokens_slices.npz", **{"0": np.ones((1, 4, 3), int)})
    upper, face = load_idle_slices(tmp_path)
    assert upper.shape == (8, 6) and face.shape == (4, 3)
    with pytest.raises(ValueError, match="idle upper tokens"):
        IdleGate(upper[:7], face, slice(0, 8), slice(16, 20))
