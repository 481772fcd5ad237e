"""Codec checkpoints: a directory with `model.safetensors`, `config.yaml` (the CodecFileConfig and the
region) and, for resuming, `optimizer.safetensors` + `trainer_state.json`.

`load_codec(directory)` rebuilds the codec from the config next to the weights. The official
release checkpoints (state_dict_keys/codec_*.tsv) use the same key names: they load with
`codec.load_state_dict(safetensors.torch.load_file(path), strict=True)` after stripping a
`module.`/`m.` prefix; the weight norm stays as (weight_g, weight_v).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
import yaml
from safetensors.torch import load_file, save_file

from ecas.core.config import load_yaml
from gesture.codec.build import build_codec
from gesture.codec.config import CodecFileConfig, codec_file_config_from_dict
from gesture.codec.model import GestureCodec

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.yaml"
OPTIMIZER_FILE = "optimizer.safetensors"
TRAINER_STATE_FILE = "trainer_state.json"


def save_codec(directory: Path, codec: GestureCodec, config: CodecFileConfig, region: str) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in codec.state_dict().items()}, str(directory / MODEL_FILE))
    (directory / CONFIG_FILE).write_text(yaml.safe_dump({"region": region, **config.to_dict()}, sort_keys=False))


def read_checkpoint_config(directory: Path) -> tuple[CodecFileConfig, str]:
    path = Path(directory) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no codec config next to the checkpoint")
    tree = load_yaml(path)
    region = tree.pop("region", None)
    if region is None:
        raise ValueError(f"{path}: missing 'region'")
    return codec_file_config_from_dict(tree), region


def load_codec(directory: str | Path, device: str | torch.device = "cpu") -> GestureCodec:
    """The codec saved in `directory`, in eval mode."""
    directory = Path(directory)
    config, region = read_checkpoint_config(directory)
    codec = build_codec(config.codec, region)
    weights = directory / MODEL_FILE
    if not weights.is_file():
        raise FileNotFoundError(f"{weights}: codec weights not found")
    codec.load_state_dict(load_file(str(weights), device=str(device)), strict=True)
    return codec.to(device).eval()


def save_optimizer(directory: Path, optimizer: torch.optim.Optimizer, trainer_state: dict) -> None:
    """Optimizer tensors to safetensors (`state.<param>.<name>`); everything else to JSON."""
    tensors, scalars = {}, {}
    for index, state in optimizer.state_dict()["state"].items():
        for name, value in state.items():
            if torch.is_tensor(value):
                tensors[f"state.{index}.{name}"] = value.contiguous()
            else:
                scalars[f"{index}.{name}"] = value
    save_file(tensors, str(directory / OPTIMIZER_FILE))
    state = {**trainer_state, "param_groups": optimizer.state_dict()["param_groups"], "optimizer_scalars": scalars}
    (directory / TRAINER_STATE_FILE).write_text(json.dumps(state, indent=1))


def load_optimizer(directory: Path, optimizer: torch.optim.Optimizer) -> dict:
    """Restore the optimizer from `directory`; return the trainer state (step, history, ...)."""
    state = json.loads((directory / TRAINER_STATE_FILE).read_text())
    per_param: dict[int, dict] = {}
    for key, value in load_file(str(directory / OPTIMIZER_FILE)).items():
        _, index, name = key.split(".", 2)
        per_param.setdefault(int(index), {})[name] = value
    for key, value in state.pop("optimizer_scalars").items():
        index, name = key.split(".", 1)
        per_param.setdefault(int(index), {})[name] = value
    optimizer.load_state_dict({"state": per_param, "param_groups": state.pop("param_groups")})
    return state
