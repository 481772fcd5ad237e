"""YAML config → frozen dataclasses. The one place that reads the config tree.

Every section's options are a frozen dataclass owned by its package (`dialogue.config.DialogueConfig`, ...).
`build_dataclass` checks every key and type and names the full key in its errors;
`__post_init__` hooks raise `ConfigError` for value checks.

Paths: an option typed `Path` that a config file gives as a relative path is taken relative to that file's directory
(`load_yaml` marks every string it reads with the file's directory, as a `FileStr`), so a config names the files
beside it wherever it is installed; a path from the command line (`--set`, or a plain string from code) stays relative
to the working directory. `~` and environment variables expand in both: a packaged config names a file under the
working directory as `$PWD/...` and one of the real recordings as `$ECAS_DATA/...` (`ecas.core.paths.data_root`).
`--config` takes a file or the name of a packaged config (`config_path`).
"""

from __future__ import annotations

import dataclasses
import os
import re
import stat
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import yaml

from ecas.core.paths import CONFIGS_DIR, DATA_ROOT_ENV, data_root


class ConfigError(ValueError):
    """A bad option; the message starts with the option's full key."""


class FileStr(str):
    """A string read from a config file, with the file's directory: a relative path in it is relative to there."""

    def __new__(cls, value: str, base_dir: Path):
        out = super().__new__(cls, value)
        out.base_dir = base_dir
        return out

    def __reduce__(self):
        return FileStr, (str(self), self.base_dir)


def resolve_path(value: str | Path) -> Path:
    """A path option's value: `~` and environment variables expanded, and a relative path read from a config file
    joined to that file's directory (normalised); any other relative path stays relative to the working directory."""
    text = _VARIABLE.sub(_expand_variable, str(value))
    path = Path(text).expanduser()
    if isinstance(value, FileStr) and not path.is_absolute():
        return Path(os.path.normpath(value.base_dir / path))
    return path


_VARIABLE = re.compile(r"\$(\w+)|\$\{(\w+)\}")


def _expand_variable(match: re.Match) -> str:
    """`$PWD` is always the working directory (a child process started with another cwd inherits its parent's
    PWD); `$ECAS_DATA` defaults to the data root; another unset variable stays as written."""
    name = match.group(1) or match.group(2)
    if name == "PWD":
        return os.getcwd()
    if name in os.environ:
        return os.environ[name]
    return str(data_root()) if name == DATA_ROOT_ENV else match.group(0)


def config_path(name: str | Path) -> Path:
    """`--config`: a YAML file, or the name of a packaged config (`default`, `miburi-release`, `lm/small`)."""
    path = Path(name)
    if path.exists() or path.suffix in (".yaml", ".yml") or path.is_absolute():
        return path
    packaged = CONFIGS_DIR / f"{name}.yaml"
    if packaged.is_file():
        return packaged
    known = sorted(str(p.relative_to(CONFIGS_DIR).with_suffix("")) for p in CONFIGS_DIR.rglob("*.yaml"))
    raise ConfigError(f"--config {name}: no such file, nor a packaged config (packaged: {', '.join(known)})")


def build_dataclass(cls: type, mapping: Mapping[str, Any] | None, path: str = "") -> Any:
    """Build dataclass `cls` from a mapping, rejecting unknown keys and wrong types by their full key."""
    mapping = {} if mapping is None else mapping
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"{path or cls.__name__}: expected a mapping, got {type(mapping).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        raise ConfigError(f"{_join(path, unknown[0])}: unknown option (known: {', '.join(sorted(fields))})")
    kwargs = {str(name): _coerce(hints[name], value, _join(path, name)) for name, value in mapping.items()}
    try:
        return cls(**kwargs)
    except TypeError as e:  # a required field is missing
        raise ConfigError(f"{path or cls.__name__}: {e}") from None


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _coerce(tp: Any, value: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(arg, value, path)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{path}: {value!r} matches none of {tp}")
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{path}: must be one of {', '.join(map(repr, args))}, got {value!r}")
        return str(value) if isinstance(value, str) else value
    if dataclasses.is_dataclass(tp):
        return build_dataclass(tp, value, path)
    if origin is tuple:
        if not isinstance(value, Sequence) or isinstance(value, str):
            raise ConfigError(f"{path}: expected a list, got {value!r}")
        item_types = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(item_types) != len(value):
            raise ConfigError(f"{path}: expected {len(item_types)} items, got {len(value)}")
        return tuple(_coerce(t, v, f"{path}[{i}]") for i, (t, v) in enumerate(zip(item_types, value)))
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{path}: expected a mapping, got {value!r}")
        key_t, val_t = args or (str, Any)
        return {_coerce(key_t, k, path): _coerce(val_t, v, _join(path, str(k))) for k, v in value.items()}
    return _coerce_scalar(tp, value, path)


def _coerce_scalar(tp: Any, value: Any, path: str) -> Any:
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, got {value!r}")
        return value
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp is Path and isinstance(value, (str, Path)):
        return resolve_path(value)
    if tp is str and isinstance(value, str):
        return str(value)  # a FileStr's directory matters only to a path
    if isinstance(tp, type) and isinstance(value, tp) and not (tp is int and isinstance(value, bool)):
        return value
    raise ConfigError(f"{path}: expected {getattr(tp, '__name__', tp)}, got {value!r}")


def parse_override(text: str) -> tuple[list[str], Any]:
    """`section.key=value` → (["section", "key"], value parsed as YAML)."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"--set {text!r}: expected section.key=value")
    return key.strip().split("."), yaml.safe_load(raw)


def apply_override(tree: dict, keys: list[str], value: Any) -> None:
    node = tree
    for i, key in enumerate(keys[:-1]):
        child = node.setdefault(key, {})
        if not isinstance(child, dict):
            raise ConfigError(f"{'.'.join(keys[: i + 1])}: is not a section, cannot set {'.'.join(keys)}")
        node = child
    node[keys[-1]] = value


class _FileLoader(yaml.SafeLoader):
    """safe_load that reads every string as a FileStr of the file's directory."""

    base_dir = Path(".")


def _file_str(loader: _FileLoader, node: yaml.ScalarNode) -> FileStr:
    return FileStr(loader.construct_scalar(node), loader.base_dir)


_FileLoader.add_constructor("tag:yaml.org,2002:str", _file_str)
yaml.SafeDumper.add_representer(FileStr, yaml.representer.SafeRepresenter.represent_str)
MAX_CONFIG_BYTES = 16_000_000


def load_yaml(path: Path) -> dict:
    """A config file's tree; its strings are FileStr, so its relative paths are relative to its directory.
    Only a regular file is read: a named pipe or a device is refused before it is opened (a pipe with no writer
    would block forever), and a file beyond MAX_CONFIG_BYTES is not read."""
    loader = type("Loader", (_FileLoader,), {"base_dir": Path(path).absolute().parent})
    try:
        mode = Path(path).stat().st_mode
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            raise ConfigError(f"{path}: is not a regular file (a named pipe or a device?); give a YAML file")
        if Path(path).stat().st_size > MAX_CONFIG_BYTES:
            raise ConfigError(f"{path}: larger than {MAX_CONFIG_BYTES // 1_000_000} MB; not a config file")
        tree = yaml.load(Path(path).read_text(), Loader=loader)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a YAML config file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the config ({getattr(e, 'strerror', None) or e})") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML: {e}") from None
    if tree is None:
        return {}
    if not isinstance(tree, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    return tree
