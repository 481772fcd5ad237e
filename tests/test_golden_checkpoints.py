"""The shipped checkpoints still produce what they produced when tests/golden/checkpoints.npz was written: the
float32 generator's sampled tokens and motion, and every step path's logits and decoded features on those tokens
(float32 to 1e-6; the reduced weight forms within the tolerances of tests/test_lm_stepper.py and
tests/test_codec_inference.py), on both kernels of each form.

After replacing ecas/checkpoints/, regenerate the file: `python -m tests.golden.checkpoints`
(tests/golden/checkpoints.py).
"""

import numpy as np
import pytest
import torch

from ecas.core.body import REGIONS
from gesture.codec.inference import INFERENCE_DTYPES
from gesture.lm.stepper import LMStepper
from gesture.nn.weights import WEIGHT_FORMS
from tests.golden.checkpoints import GOLDEN, decode, generate, generator, lm_logits, load_shipped
from tests.kernels import KERNELS, using

torch.set_num_threads(1)
FLOAT32 = 1e-6  # relative to the largest magnitude: float32 runs the same products in the same order
LM_REDUCED = 0.05  # bfloat16 / int8 logits (tests/test_lm_stepper.py)
CODEC_REDUCED = {"float16": 5e-3, "bfloat16": 3e-2, "int8": 5e-2}  # tests/test_codec_inference.py


@pytest.fixture(scope="module")
def shipped():
    return load_shipped()


@pytest.fixture(scope="module")
def golden():
    with np.load(GOLDEN) as stored:
        return dict(stored)


def _close(got: np.ndarray, want: np.ndarray, relative: float) -> None:
    np.testing.assert_allclose(got, want, rtol=0, atol=relative * float(np.abs(want).max()))


def test_the_float32_generator_samples_the_same_tokens_and_motion(shipped, golden):
    gen = generator(*shipped)
    got = generate(gen, golden["text"], golden["audio"])
    gen.close()
    np.testing.assert_array_equal(got["tokens"], golden["tokens"])
    for key in ("poses", "trans", "expressions"):
        _close(got[key], golden[key], FLOAT32)


@pytest.mark.parametrize("kernels", KERNELS)
@pytest.mark.parametrize("form", WEIGHT_FORMS)
def test_every_lm_step_path_gives_the_stored_logits(shipped, golden, form, kernels):
    lm, _ = shipped
    with using(kernels, form):
        stepper = LMStepper(lm, guided=True, dtype=form)
        got = lm_logits(stepper, golden["tokens"], golden["text"], golden["audio"])
    _close(got, golden["logits"], FLOAT32 if form == "float32" else LM_REDUCED)


@pytest.mark.parametrize("kernels", KERNELS)
@pytest.mark.parametrize("form", INFERENCE_DTYPES)
@pytest.mark.parametrize("region", REGIONS)
def test_every_codec_step_path_decodes_the_stored_features(shipped, golden, region, form, kernels):
    lm, codecs = shipped
    gen_slices = generator(lm, codecs).level_slices
    with using(kernels, form):
        got = decode(codecs[region], golden["tokens"][:, gen_slices[region]], form)
    _close(got, golden[f"decoded_{region}"], FLOAT32 if form == "float32" else CODEC_REDUCED[form])
