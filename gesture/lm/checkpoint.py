"""Gesture LM checkpoints: a directory with `lm.safetensors` (weights), `lm.json` (model sizes, the condition
spec it was trained with, epoch/step) and, while training, `train_state.pt` (optimizer, scheduler, RNG)."""

from __future__ import annotations

import dataclasses
import json
import pickle
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from ecas.core.config import build_dataclass
from ecas.core.spec import ConditionSpec
from gesture.lm.config import LMConfig
from gesture.lm.model import GestureLM

WEIGHTS_FILE = "lm.safetensors"
META_FILE = "lm.json"
CHECKPOINT_PREFIXES = ("module.", "m.")


class CheckpointError(ValueError):
    """A checkpoint file is unreadable or holds something else than it should; the message is one line."""


def save_lm(model: GestureLM, directory: Path, **progress: int) -> None:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(directory / WEIGHTS_FILE))
    meta = {"lm": dataclasses.asdict(model.sizes), "condition": model.spec.to_dict(), **progress}
    (directory / META_FILE).write_text(json.dumps(meta, indent=2))


def read_meta(directory: Path) -> dict:
    path = Path(directory) / META_FILE
    if not path.exists():
        raise FileNotFoundError(f"{directory}: not a gesture LM checkpoint ({META_FILE} is missing)")
    return json.loads(path.read_text())


def load_lm(directory: Path, expected_spec: ConditionSpec | None = None) -> GestureLM:
    """Build the model of a checkpoint directory; with `expected_spec`, refuse a checkpoint trained on another
    conditioning vocabulary (a clear `SpecMismatchError`, never garbage tokens)."""
    meta = read_meta(directory)
    spec = ConditionSpec.from_dict(meta["condition"])
    if expected_spec is not None:
        spec.check_compatible(expected_spec, f"gesture LM checkpoint {directory}")
    model = GestureLM(build_dataclass(LMConfig, meta["lm"], "lm"), spec)
    state = load_file(str(Path(directory) / WEIGHTS_FILE))
    state = {_strip_prefix(k): v.float() for k, v in state.items()}
    model.load_state_dict(state, strict=True)
    return model.eval()


def _strip_prefix(key: str) -> str:
    for prefix in CHECKPOINT_PREFIXES:
        if key.startswith(prefix):
            return key[len(prefix) :]
    return key


def save_train_state(
    directory: Path, optimizer: torch.optim.Optimizer, scheduler, generator: torch.Generator, losses: list[dict]
) -> None:
    torch.save(
        {
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
            "generator": generator.get_state(),
            "losses": losses,
        },
        Path(directory) / "train_state.pt",
    )


def load_train_state(directory: Path) -> dict | None:
    """The optimizer, scheduler, RNG and losses of a resumed run, or None. `weights_only=True`: the file may hold
    tensors, numbers, strings and containers only, so a planted file cannot run code (CheckpointError instead)."""
    path = Path(directory) / "train_state.pt"
    if not path.exists():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError) as err:
        first = next((line for line in str(err).splitlines() if line.strip()), type(err).__name__)
        raise CheckpointError(f"{path}: not a training state this project wrote ({first.strip()})") from None
    if not isinstance(state, dict) or not {"optimizer", "scheduler", "generator", "losses"} <= state.keys():
        raise CheckpointError(f"{path}: not a training state this project wrote (its keys are not ours)")
    return state
