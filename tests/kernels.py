"""Run reduced-precision tests on both kernels of a weight form: the fast one where this CPU has it, the portable
one always (`gesture.nn.weights`)."""

import contextlib

import pytest

from gesture.nn.weights import FAST_KERNEL_NEEDS, fast_kernel_error, portable_forced, portable_kernels

KERNELS = ("fast", "portable")


def using(kernels: str, form: str) -> contextlib.AbstractContextManager:
    """A context in which `form` is stored with `kernels` ("fast" or "portable"); skips the test when "fast" is
    asked of a form whose fast kernel this CPU cannot run (or while the portable kernels are forced)."""
    if kernels == "portable":
        return portable_kernels(True)
    if form in FAST_KERNEL_NEEDS and (portable_forced() or fast_kernel_error(form) is not None):
        pytest.skip(f"no fast {form} kernel here: {fast_kernel_error(form) or 'portable kernels forced'}")
    return contextlib.nullcontext()
