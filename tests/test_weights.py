"""gesture.nn.weights: every form runs on this CPU with the kernel its probe allows, both kernels of a form agree,
the portable kernels can be forced, and a form this CPU cannot run fast is named in one line."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gesture.nn import weights
from gesture.nn.weights import (
    PORTABLE_ENV,
    WEIGHT_FORMS,
    UnsupportedFormError,
    fast_kernel_error,
    kernel_for,
    kernels_used,
    portable_kernels,
    quantize_int8_rows,
    require_fast_form,
    step_weight,
    stored_weights,
)
from tests.kernels import KERNELS, using

# Largest |product - float32| relative to max |float32 product| for 64 inputs: float16 rounds operands to 2^-11,
# bfloat16 to 2^-8 (inputs and output); int8 adds max|row|/254 per weight.
TOLERANCE = {"float32": 1e-6, "float16": 2e-3, "bfloat16": 2e-2, "int8": 3e-2}
PORTABLE = {
    "float32": "dense-float32",
    "float16": "dense-float16",
    "bfloat16": "dense-bfloat16",
    "int8": "int8-in-bf16",
}


def _matrix(out_features=40, in_features=64, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(out_features, in_features, generator=generator), torch.randn(3, in_features, generator=generator)


@pytest.mark.parametrize("kernels", KERNELS)
@pytest.mark.parametrize("form", WEIGHT_FORMS)
def test_every_form_computes_the_product(form, kernels):
    matrix, x = _matrix()
    with using(kernels, form):
        weight = step_weight(matrix, form)
    if kernels == "portable":
        assert weight.kernel == PORTABLE[form]
    got = weight.apply(x)
    assert got.dtype == weight.out_dtype and got.shape == (3, 40)
    want = x @ matrix.T
    assert float((got.float() - want).abs().max()) <= TOLERANCE[form] * float(want.abs().max())


@pytest.mark.parametrize("form", ["bfloat16", "int8"])
def test_fast_and_portable_kernels_agree_to_bfloat16_rounding(form):
    if fast_kernel_error(form) is not None:
        pytest.skip(f"no fast {form} kernel here: {fast_kernel_error(form)}")
    matrix, x = _matrix()
    with portable_kernels(False):
        fast = step_weight(matrix, form)
    with portable_kernels(True):
        portable = step_weight(matrix, form)
    assert fast.kernel != portable.kernel
    scale = float(fast.apply(x).float().abs().max())
    torch.testing.assert_close(fast.apply(x).float(), portable.apply(x).float(), atol=2**-7 * scale, rtol=0)


def test_int8_quantization_rounds_each_row_to_its_own_scale():
    matrix, _ = _matrix()
    quantized, scale = quantize_int8_rows(matrix)
    assert quantized.dtype == torch.int8 and int(quantized.abs().max()) == 127
    assert bool(((quantized.float() * scale[:, None] - matrix).abs() <= scale[:, None] / 2 + 1e-7).all())


def test_int8_rows_the_int8_kernel_cannot_take_are_stored_as_bfloat16():
    assert kernel_for("int8", 24) == kernel_for("bfloat16", 24)  # 24 inputs: not a multiple of 16
    matrix, x = _matrix(in_features=24)
    weight = step_weight(matrix, "int8")
    assert weight.out_dtype == torch.bfloat16
    torch.testing.assert_close(weight.apply(x).float(), x @ matrix.T, atol=0.1, rtol=0.03)


def test_the_environment_forces_the_portable_kernels():
    code = "from gesture.nn.weights import kernel_for; print(kernel_for('bfloat16', 64), kernel_for('int8', 64))"
    forced = subprocess.run(
        [sys.executable, "-c", code], env={**_env(), PORTABLE_ENV: "1"}, capture_output=True, text=True, check=True
    )
    assert forced.stdout.split() == ["dense-bfloat16", "int8-in-bf16"]


def _env():
    return {k: v for k, v in os.environ.items() if k != PORTABLE_ENV}


def test_a_form_without_its_fast_kernel_is_named_in_one_line(monkeypatch, caplog):
    if fast_kernel_error("bfloat16") is None:  # a CPU that has it: stand in a failed probe for this check
        monkeypatch.setattr(weights, "fast_kernel_error", lambda form: "simulated: kernel missing")
    with portable_kernels(False), pytest.raises(UnsupportedFormError) as stopped:
        require_fast_form("bfloat16", "gesture.dtype", fallback=False)
    message = str(stopped.value)
    assert "\n" not in message and message.startswith("gesture.dtype=bfloat16: the fast onednn-bf16 kernel needs")
    assert "avx512bw" in message and "this CPU (" in message
    with portable_kernels(False), caplog.at_level("WARNING"):
        assert require_fast_form("bfloat16", "gesture.dtype", fallback=True) == "bfloat16"
    assert any("using the portable kernel" in r.getMessage() for r in caplog.records)
    assert require_fast_form("float32", "gesture.dtype", fallback=False) == "float32"


def test_bad_form_names_the_option():
    with pytest.raises(ValueError, match="gesture.dtype: must be one of float32, float16, bfloat16, int8, got 'fp8'"):
        require_fast_form("fp8", "gesture.dtype", fallback=True)


def test_stored_weights_are_found_and_counted_once():
    matrix, _ = _matrix()
    shared = step_weight(matrix, "int8")
    tree = {"a": [shared, (shared, step_weight(matrix, "float32"))], "b": object()}
    found = stored_weights(tree)
    assert len(found) == 2
    assert sum(w.nbytes for w in found) == 40 * 64 * 4 + shared.nbytes
    assert shared.nbytes in (40 * 64 + 40 * 2, 40 * 64 * 2 + 40 * 2)  # int8 values, or held in bfloat16; scales
    assert sum(kernels_used(tree).values()) == 2


def test_launch_stops_in_one_line_when_the_cpu_cannot_run_the_form_and_fallback_is_off(tmp_path):
    if fast_kernel_error("bfloat16") is not None:
        expected_code, expected = 2, "error: gesture.dtype=bfloat16: the fast onednn-bf16 kernel needs"
    else:
        pytest.skip("this CPU runs oneDNN's bf16 kernel (the stop itself is tested above with a failed probe)")
    root = Path(__file__).resolve().parents[1]
    report = tmp_path / "report"
    speech = root.parent / "shared/data/speech/librivox_0870.wav"
    done = subprocess.run(
        [
            sys.executable,
            "launch.py",
            "--replay",
            str(speech),
            "--headless",
            "--report",
            str(report),
            "--set",
            "gesture.dtype=bfloat16",
            "--set",
            "gesture.dtype_fallback=false",
        ],
        cwd=root,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == expected_code
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(expected) and "gesture.dtype_fallback=true" in lines[0]
    assert not report.exists()  # nothing started
