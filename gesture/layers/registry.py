"""The registry of runtime layers: name -> (options dataclass, builder), filled by `@register` in each layer's file.

    specs = parse_layers(tree["gesture"]["layers"], "gesture.layers")  # validated once, errors name the option
    layers = build_layers(specs, LayerEnv(seed=0, levels=...))        # the objects the generator steps, in order

The config lists layers in order, each item one mapping `name: {options}` (or the bare name for the defaults). Every
module of this package is imported before a name is looked up, so a new layer is its own file (with `@register`)
and its line in the config, nothing else.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

from ecas.core.config import ConfigError, build_dataclass
from gesture.layers.base import Layer, LayerEnv, LayerOptionError, Stage


@dataclass(frozen=True)
class Entry:
    options: type  # the layer's frozen options dataclass
    build: Callable[[Any, LayerEnv], Layer]
    stage: Stage


@dataclass(frozen=True)
class LayerSpec:
    """One item of `gesture.layers`: the layer's name and its validated options."""

    name: str
    options: Any


_ENTRIES: dict[str, Entry] = {}


def register(name: str, options: type, stage: Stage = "motion"):
    """Decorator of a layer's builder `build(options, env) -> layer` under `name` with its options dataclass."""

    def decorate(build: Callable[[Any, LayerEnv], Layer]):
        if name in _ENTRIES and _ENTRIES[name].build is not build:
            raise ValueError(f"layer {name!r}: registered twice")
        _ENTRIES[name] = Entry(options, build, stage)
        return build

    return decorate


@cache
def _import_layers() -> None:
    package = importlib.import_module(__package__)
    for module in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"{__package__}.{module.name}")


def known_layers() -> dict[str, Entry]:
    _import_layers()
    return dict(sorted(_ENTRIES.items()))


def _entry(name: str, path: str) -> Entry:
    entries = known_layers()
    if name not in entries:
        raise ConfigError(f"{path}: unknown layer {name!r} (known: {', '.join(entries)})")
    return entries[name]


def parse_layer(item: Any, path: str) -> LayerSpec:
    """One config item (`{name: options}`, a bare name, or a LayerSpec) -> its LayerSpec, options validated."""
    if isinstance(item, LayerSpec):
        item = {item.name: item.options}
    if isinstance(item, str):
        item = {item: None}
    if not isinstance(item, Mapping) or len(item) != 1:
        raise ConfigError(f"{path}: expected one layer as `name: {{options}}`, got {item!r}")
    ((name, raw),) = item.items()
    entry = _entry(str(name), path)
    where = f"{path}.{name}"
    if isinstance(raw, entry.options):
        return LayerSpec(name, raw)
    try:
        return LayerSpec(name, build_dataclass(entry.options, raw, where))
    except LayerOptionError as error:
        raise ConfigError(f"{where}.{error}") from None


def parse_layers(items: Sequence[Any], path: str = "gesture.layers") -> tuple[LayerSpec, ...]:
    """The ordered list of `gesture.layers` -> LayerSpecs. Token layers act before decoding: they must come first."""
    if isinstance(items, (str, Mapping)) or not isinstance(items, Sequence):
        raise ConfigError(f"{path}: expected a list of layers, got {items!r}")
    specs = tuple(parse_layer(item, f"{path}[{i}]") for i, item in enumerate(items))
    stages = [known_layers()[s.name].stage for s in specs]
    if "motion" in stages and "tokens" in stages[stages.index("motion") :]:
        late = stages.index("tokens", stages.index("motion"))
        raise ConfigError(
            f"{path}[{late}].{specs[late].name}: a token layer acts before decoding, so it must come before every "
            f"motion layer (here after {specs[stages.index('motion')].name})"
        )
    return specs


def build_layers(specs: Sequence[LayerSpec], env: LayerEnv, path: str = "gesture.layers") -> list[Layer]:
    """The layers of `specs`, built in order; a builder's ValueError names the layer's place in the config."""
    layers = []
    for i, spec in enumerate(specs):
        where = f"{path}[{i}].{spec.name}"
        try:
            layers.append(_entry(spec.name, where).build(spec.options, env))
        except LayerOptionError as error:
            raise ConfigError(f"{where}.{error}") from None
        except FileNotFoundError as error:
            raise FileNotFoundError(f"{where}.{error}") from None
        except ValueError as error:
            if isinstance(error, ConfigError):
                raise
            raise ConfigError(f"{where}: {error}") from None
    return layers


def build_layer(name: str, options: Any = None, env: LayerEnv | None = None) -> Layer:
    """One layer from its options (a mapping, the options dataclass, or None for the defaults), as if it were the
    only item of `gesture.layers`."""
    return build_layers(parse_layers([{name: options}]), env or LayerEnv())[0]
