"""The cached step path equals the teacher-forced full-sequence forward (incl. after the ring caches wrap)."""

import pytest
import torch

from gesture.lm.naive import NaiveStepper
from gesture.lm.stepper import LMStepper
from tests.kernels import KERNELS, using
from tests.lm_fixtures import tiny_lm

torch.set_num_threads(1)
STEPS = 200


def _sequence(model, steps, seed=3):
    g = torch.Generator().manual_seed(seed)
    s, spec = model.sizes, model.spec
    tokens = torch.randint(0, s.card, (s.n_levels, steps), generator=g)
    text = torch.randint(-1, spec.text_vocab, (steps,), generator=g)
    audio = torch.randint(-1, spec.audio_card, (spec.n_audio_codebooks, steps), generator=g)
    return tokens, text, audio


def _full_logits(model, tokens, text, audio, speaker, guided):
    """(B, T, K, V): row 0 conditioned, row 1 (guided) the null condition with the same history."""
    rows = 2 if guided else 1
    text_b = torch.stack([text, torch.full_like(text, -1)])[:rows]
    audio_b = torch.stack([audio, torch.full_like(audio, -1)])[:rows]
    with torch.no_grad():
        return model(tokens[None].expand(rows, -1, -1), text_b, audio_b, torch.tensor([speaker] * rows)).logits


def _stream_logits(engine, tokens, text, audio):
    """Logits (B, T, K, V) of the tokens teacher-forced through a step path, continuing its stream if it has one."""
    if not engine.is_streaming:
        engine.start_streaming(engine.batch)
    out = []
    with torch.inference_mode():
        for t in range(tokens.shape[1]):
            history = tokens[:, t - 1] if t else torch.full((tokens.shape[0],), -1)
            step = [engine.begin_step(history, int(text[t]), audio[:, t])]
            step += [engine.depth_logits(k, int(tokens[k, t])) for k in range(tokens.shape[0] - 1)]
            out.append(torch.stack(step, dim=1))  # (B, K, V)
    return torch.stack(out, dim=1)  # (B, T, K, V)


@pytest.mark.parametrize("guided, contexts", [(False, (6, 9)), (True, (6, 9)), (True, (25, 50))])
def test_streaming_equals_full_forward_over_200_steps(guided, contexts):
    model = tiny_lm(va_use_face_logits=True, self_context_steps=contexts[0], cross_context_steps=contexts[1])
    assert STEPS > 3 * model.sizes.cross_context_steps  # every ring wraps several times
    tokens, text, audio = _sequence(model, STEPS)
    full = _full_logits(model, tokens, text, audio, 2, guided)
    stepper = LMStepper(model, guided)
    stepper.set_speaker(2)
    streamed = _stream_logits(stepper, tokens, text, audio)
    assert (streamed - full).abs().max() < 1e-4


def test_reset_restarts_the_stream_exactly():
    model = tiny_lm()
    tokens, text, audio = _sequence(model, 30)
    stepper = LMStepper(model, guided=True)
    first = _stream_logits(stepper, tokens, text, audio)
    stepper.reset_streaming()
    assert torch.equal(_stream_logits(stepper, tokens, text, audio), first)


def test_naive_baseline_equals_cached_path():
    model = tiny_lm()
    tokens, text, audio = _sequence(model, 24)  # > the naive window of 19 steps
    cached = _stream_logits(LMStepper(model, guided=True), tokens, text, audio)
    naive = _stream_logits(NaiveStepper(model, guided=True), tokens, text, audio)
    assert (cached - naive).abs().max() < 1e-4


def test_va_head_of_the_step_path_equals_full_forward():
    model = tiny_lm(va_use_face_logits=True)
    tokens, text, audio = _sequence(model, 12)
    with torch.no_grad():
        full = model(tokens[None], text[None], audio[None], torch.tensor([0])).va_logit[0]
    stepper = LMStepper(model, guided=False)
    stepper.start_streaming(1)
    face = model.sizes.face_levels
    with torch.inference_mode():
        for t in range(12):
            history = tokens[:, t - 1] if t else torch.full((model.sizes.n_levels,), -1)
            stepper.begin_step(history, int(text[t]), audio[:, t])
            logits = [stepper.depth_logits(k, int(tokens[k, t])) for k in range(model.sizes.n_depth)]
            face_logits = torch.stack([logits[level - 1][0] for level in face])
            assert abs(stepper.va_logit(face_logits) - float(full[t])) < 1e-4


@pytest.mark.parametrize("kernels", KERNELS)
@pytest.mark.parametrize("dtype", ["bfloat16", "int8"])
def test_reduced_precision_weights_stay_close_to_float32(dtype, kernels):
    """Measured on the shipped checkpoint: ~0.5% (bfloat16) and ~1% (per-row int8) of max |logit|."""
    model = tiny_lm()
    tokens, text, audio = _sequence(model, 30)
    ref = _stream_logits(LMStepper(model, guided=True), tokens, text, audio)
    with using(kernels, dtype):
        stepper = LMStepper(model, guided=True, dtype=dtype)
    low = _stream_logits(stepper, tokens, text, audio)
    assert (low - ref).abs().max() < 0.05 * ref.abs().max()


# bfloat16 products round each logit to 2^-8 relative; guidance c = 3 adds the rows' roundings (c + |c - 1| = 5 ulps)
@pytest.mark.parametrize("kernels", KERNELS)
@pytest.mark.parametrize("dtype, tolerance", [("float32", 1e-5), ("bfloat16", 0.05), ("int8", 0.05)])
def test_guided_logits_equal_guidance_of_the_rows(dtype, tolerance, kernels):
    """The guided row is the classifier of the lerped hidden state: null + c (cond − null) of the two rows (within
    `tolerance` x max |logit| for the rounded weight forms); guidance 1 is row 0."""
    model = tiny_lm()
    tokens, text, audio = _sequence(model, 8)
    with using(kernels, dtype):
        rows_engine, guided_engine = LMStepper(model, True, dtype), LMStepper(model, True, dtype)
    rows_engine.start_streaming(2)
    guided_engine.start_streaming(2)

    def check(rows, guided):
        scale = rows.abs().max() if dtype != "float32" else 1.0
        torch.testing.assert_close(guided, rows[1] + 3.0 * (rows[0] - rows[1]), atol=tolerance * scale, rtol=0)

    with torch.inference_mode():
        for t in range(8):
            history = tokens[:, t - 1] if t else torch.full((model.sizes.n_levels,), -1)
            check(
                rows_engine.begin_step(history, int(text[t]), audio[:, t]),
                guided_engine.begin_step(history, int(text[t]), audio[:, t], 3.0),
            )
            for k in range(model.sizes.n_depth):
                rows = rows_engine.depth_logits(k, int(tokens[k, t]))
                check(rows, guided_engine.depth_logits(k, int(tokens[k, t]), 3.0))
                plain = rows_engine.depth_logits(k, int(tokens[k, t]), 1.0)
                torch.testing.assert_close(plain, rows[0], atol=tolerance * rows.abs().max(), rtol=0)


def test_unknown_weight_dtype_names_the_option():
    with pytest.raises(ValueError, match="dtype"):
        LMStepper(tiny_lm(), guided=True, dtype="fp16")


def test_the_step_path_follows_the_streaming_contract():
    stepper = LMStepper(tiny_lm(), guided=True)
    history = torch.full((stepper.sizes.n_levels,), -1)
    with pytest.raises(RuntimeError, match="start_streaming"):
        stepper.begin_step(history, 0, torch.zeros(8, dtype=torch.long))
    with pytest.raises(ValueError, match="2 rows"):
        stepper.start_streaming(1)
    with stepper.streaming(2):
        assert stepper.is_streaming and stepper.state.step == 0
    assert not stepper.is_streaming
