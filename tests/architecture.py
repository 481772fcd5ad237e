"""The layers of the code, lowest first, and a checker that reads every module's imports with ast (none is run).

A module belongs to the longest component (a package or module path) of `LAYERS` that prefixes it. It may import
its own component and the components of lower layers; anything else is an upward (or sideways) import. Imports
inside functions count too: a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

LAYERS: tuple[tuple[str, ...], ...] = (
    ("ecas.core",),  # timing, body constants, spec, messages, bus, config loader, component contract
    ("gesture.nn", "gesture.body"),  # network blocks and step weights; body maths
    ("dialogue", "gesture.data", "gesture.layers"),  # the dialogue system; reading motion data; the runtime layers
    ("render", "gesture.synth", "gesture.codec"),  # the avatar; synthetic conversations; the motion codecs
    ("gesture.lm",),  # the gesture LM, its tokenized data and its fast step
    ("gesture",),  # the gesture runtime: generator, stage component, `gesture:` section
    ("gesture.release",),  # the MIBURI release converter
    ("gesture.eval",),  # metrics, evaluation, quality suite, realism report
    ("agent",),  # the application: sections, supervisor, stage runner, io, dashboard
    ("bench", "scripts", "ecas"),  # entry points: the `ecas` command (ecas.cli, ecas.launch), benches, scripts
    ("launch",),  # launch.py in a checkout: the design's name for `ecas`
)
ROOTS = frozenset(c.split(".")[0] for layer in LAYERS for c in layer)


@dataclass(frozen=True)
class Violation:
    module: str
    imported: str
    why: str

    def __str__(self) -> str:
        return f"{self.module} imports {self.imported}: {self.why}"


def module_names(root: Path) -> dict[str, Path]:
    """Every first-party module under `root`: dotted name -> file."""
    names = {}
    for top in sorted(ROOTS):
        for path in sorted(root.glob(f"{top}.py")) + sorted((root / top).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return names


def imports_of(source: str, modules: Iterable[str]) -> set[str]:
    """The first-party modules a module's source imports (a `from package import module` names the module)."""
    known = set(modules)
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.update(
                f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in known else node.module for a in node.names
            )
    return {name for name in found if name.split(".")[0] in ROOTS}


def import_graph(root: Path) -> dict[str, set[str]]:
    modules = module_names(root)
    return {name: imports_of(path.read_text(), modules) for name, path in modules.items()}


def component(module: str, layers: Sequence[Sequence[str]] = LAYERS) -> tuple[str, int] | None:
    """(component, layer index) of `module`, or None when no layer holds it."""
    best = None
    for rank, layer in enumerate(layers):
        for name in layer:
            if (module == name or module.startswith(name + ".")) and (best is None or len(name) > len(best[0])):
                best = (name, rank)
    return best


def layer_violations(graph: Mapping[str, set[str]], layers: Sequence[Sequence[str]] = LAYERS) -> list[Violation]:
    out = []
    for module, imported in sorted(graph.items()):
        own = component(module, layers)
        for target in sorted(imported):
            their = component(target, layers)
            if own is None:
                out.append(Violation(module, target, "the module is in no layer"))
            elif their is None:
                out.append(Violation(module, target, "the imported module is in no layer"))
            elif their[0] != own[0] and their[1] >= own[1]:
                where = "the same layer" if their[1] == own[1] else "a higher layer"
                out.append(Violation(module, target, f"{their[0]} is in {where} than {own[0]}"))
    return out


def cycles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The import cycles between modules (strongly connected groups of more than one module), each sorted."""
    index, low, stack, on_stack, groups = {}, {}, [], set(), []

    def visit(node: str) -> None:  # Tarjan's algorithm
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                group.append(top)
                if top == node:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(groups)
