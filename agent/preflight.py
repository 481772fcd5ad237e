"""Everything a stage would find wrong at its start, found by the launcher before any stage starts (in a forked
child, so what the checks load never stays in the launcher).

Each check raises ConfigError with one line naming the option: the command line's non-UTF-8 bytes, the
`run.components` entries (imported), the gesture stage's checkpoints (every safetensors file opened, its
header and tensors read and refused when not finite; the generator built exactly as the stage builds it, so
shapes, the condition spec and option ranges such as `gesture.hold_levels` are checked against the checkpoint),
the render stage's body model, and the avatar the page will draw (`--avatar`: a glTF binary with humanoid bones).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from agent.sections import AppConfig
from ecas.core.config import ConfigError

PIPE_MESSAGE_BYTES = 4000  # below PIPE_BUF: the child's one line arrives whole


def one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def check_utf8_arguments(argv: Sequence[str]) -> None:
    """A file name or value with bytes that are not UTF-8 (argparse keeps them as surrogates)."""
    for arg in argv:
        try:
            arg.encode("utf-8")
        except UnicodeEncodeError:
            raise ConfigError(
                f"the argument {ascii(arg)} holds bytes that are not UTF-8; rename the file or give a UTF-8 value"
            ) from None


def check_components(app: AppConfig) -> None:
    """Every `run.components` entry of this host's stages imports and names a callable."""
    for stage, factory in app.run.components.items():
        if stage not in app.run.local_stages:
            continue
        module, _, attr = factory.partition(":")
        try:
            made = getattr(importlib.import_module(module), attr)
        except Exception as err:  # an import runs the module's code: anything may be raised
            raise ConfigError(f"run.components.{stage}: cannot import {factory!r} ({one_line(err)})") from None
        if not callable(made):
            raise ConfigError(f"run.components.{stage}: {factory!r} is not a function")


def check_finite_weights(directory: Path, option: str) -> None:
    """Open every safetensors file under `directory`: a truncated file, a broken header or a NaN/inf weight."""
    import torch
    from safetensors import safe_open

    for path in sorted(Path(directory).rglob("*.safetensors")):
        try:
            with safe_open(str(path), framework="pt") as f:
                for key in f.keys():
                    if not torch.isfinite(f.get_tensor(key)).all():
                        raise ConfigError(
                            f"{option}: {path} holds non-finite weights in {key!r}; retrain or restore it"
                        )
        except ConfigError:
            raise
        except Exception as err:  # safetensors raises its own SafetensorError (and OSError, ValueError)
            raise ConfigError(f"{option}: {path} is not a readable safetensors file ({one_line(err)})") from None


def check_gesture_stage(app: AppConfig) -> None:
    """The shipped gesture stage's checkpoints and options, as the stage itself will build them."""
    if "gesture" not in app.run.local_stages or "gesture" in app.run.components:
        return
    from gesture.process import build_generator

    check_finite_weights(Path(app.gesture.lm_checkpoint), "gesture.lm_checkpoint")
    check_finite_weights(Path(app.gesture.codec_checkpoints), "gesture.codec_checkpoints")
    try:
        generator = build_generator(app.gesture, app.run.seed)
    except ConfigError:
        raise
    except Exception as err:
        text = " ".join(str(err).split())
        if text.split(":")[0] in {f.name for f in dataclasses.fields(app.gesture)}:
            raise ConfigError(f"gesture.{text}") from None  # e.g. "hold_levels: must be token levels in [0, 7]"
        raise ConfigError(f"gesture: the stage cannot start with this config ({one_line(err)})") from None
    generator.close()


def check_weight_form(app: AppConfig) -> None:
    """A gesture.dtype this CPU cannot run fast: one warning line now, or (gesture.dtype_fallback false) a stop."""
    from gesture.nn.weights import FAST_KERNEL_NEEDS, UnsupportedFormError, require_fast_form

    if "gesture" not in app.run.local_stages or app.gesture.dtype not in FAST_KERNEL_NEEDS:
        return
    try:
        require_fast_form(app.gesture.dtype, "gesture.dtype", app.gesture.dtype_fallback, "gesture.dtype_fallback")
    except UnsupportedFormError as e:
        raise ConfigError(str(e)) from None


def check_render_stage(app: AppConfig) -> None:
    if "render" not in app.run.local_stages or "render" in app.run.components or not app.render.body_model:
        return
    from render.body_model import BodyModelError, load_smplx_model

    try:
        load_smplx_model(app.render.body_model)
    except BodyModelError as err:
        raise ConfigError(str(err)) from None


def check_browser_page(app: AppConfig) -> None:
    """render.mode browser with the dashboard: the page's JavaScript (three.js, three-vrm) must be installed."""
    if app.render.mode != "browser" or not app.dashboard.enabled:
        return
    from agent.dashboard.vendor import missing

    if missing():
        raise ConfigError(missing())


def check_before_start(app: AppConfig) -> None:
    """Every check above, in a forked child: the checkpoints and their imports (torch, ~360 MB) stay out of the
    launcher, which lives as long as the run. ConfigError with the child's one line."""
    sys.stdout.flush()
    sys.stderr.flush()
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: check, write the one line (or nothing), leave without the parent's exit handlers
        os.close(read_end)
        try:
            _check_all(app)
        except ConfigError as err:
            os.write(write_end, str(err).encode("utf-8", "replace")[:PIPE_MESSAGE_BYTES])
        except BaseException as err:  # anything else is still one line, never a traceback
            os.write(write_end, f"the checks before the start failed ({one_line(err)})".encode()[:PIPE_MESSAGE_BYTES])
        finally:
            os._exit(0)
    os.close(write_end)
    with os.fdopen(read_end, "rb") as pipe:
        message = pipe.read().decode("utf-8", "replace")
    _, wait_status = os.waitpid(pid, 0)
    if message:
        raise ConfigError(message)
    if os.WIFSIGNALED(wait_status):
        raise ConfigError(
            f"the checks before the start died ({signal.Signals(os.WTERMSIG(wait_status)).name}); "
            "out of memory? see the system log"
        )


def check_avatar(app: AppConfig) -> None:
    """`render.avatar` (`--avatar`) is read by the dashboard when the page first asks for it: read it now."""
    if not app.render.avatar:
        return
    from render.rig import RigError, load_rig

    try:
        load_rig(app.render.avatar)
    except RigError as err:
        raise ConfigError(str(err).replace("--avatar", "render.avatar (--avatar)", 1)) from None


def _check_all(app: AppConfig) -> None:
    check_browser_page(app)
    check_components(app)
    check_weight_form(app)
    check_gesture_stage(app)
    check_render_stage(app)
    check_avatar(app)
