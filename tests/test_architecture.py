"""The layers hold: no module imports upward or sideways (tests/architecture.py draws them), and no modules import
each other in a cycle. The checker itself must catch a deliberately added upward import and a cycle."""

from pathlib import Path

from tests.architecture import LAYERS, component, cycles, import_graph, layer_violations

REPO = Path(__file__).resolve().parents[1]


def test_no_upward_import_in_the_repository():
    violations = layer_violations(import_graph(REPO))
    assert not violations, "\n".join(map(str, violations))


def test_no_import_cycle_in_the_repository():
    assert cycles(import_graph(REPO)) == []


def test_every_module_is_in_a_layer():
    unplaced = [m for m in import_graph(REPO) if component(m) is None]
    assert unplaced == []


def _tree(root: Path, files: dict[str, str]) -> Path:
    for name, source in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(source)
    return root


def test_an_added_upward_import_fails(tmp_path):
    root = _tree(
        tmp_path,
        {
            "ecas/__init__.py": "",
            "ecas/core/__init__.py": "",
            "ecas/core/timing.py": "STEP_MS = 80\n",
            "gesture/__init__.py": "",
            "gesture/body/__init__.py": "",
            "gesture/body/skeleton.py": "from ecas.core.timing import STEP_MS\n",
            "agent/__init__.py": "",
            "agent/stage.py": "from gesture.body import skeleton\n",
        },
    )
    assert layer_violations(import_graph(root)) == []
    (root / "gesture/body/skeleton.py").write_text("def f():\n    from agent.stage import Runner\n")
    (violation,) = layer_violations(import_graph(root))
    assert (violation.module, violation.imported) == ("gesture.body.skeleton", "agent.stage")
    assert "higher layer" in violation.why


def test_a_sideways_import_between_siblings_fails():
    graph = {"render.avatar": {"dialogue.tts"}, "dialogue.tts": set()}
    layers = (("ecas.core",), ("dialogue", "render"))
    (violation,) = layer_violations(graph, layers)
    assert "same layer" in violation.why


def test_a_cycle_is_found():
    graph = {
        "gesture.eval.suite": {"gesture.eval.evaluate"},
        "gesture.eval.evaluate": {"gesture.eval.suite"},
        "gesture.eval.metrics": set(),
    }
    assert cycles(graph) == [["gesture.eval.evaluate", "gesture.eval.suite"]]


def test_the_core_imports_no_stage():
    assert LAYERS[0] == ("ecas.core",)
    stages = {"agent", "dialogue", "gesture", "render"}
    graph = import_graph(REPO)
    assert not {t.split(".")[0] for m, ts in graph.items() if m.startswith("ecas.core.") for t in ts} & stages


def test_every_ecas_command_is_a_module_with_a_main():
    """`ecas COMMAND` runs a module's `main`: every module the command table names exists, defines `main`, runs it
    under `python -m`, and names itself `ecas COMMAND` in its usage line."""
    from ecas.cli import COMMANDS

    for name, (module, _) in COMMANDS.items():
        path = REPO / (module.replace(".", "/") + ".py")
        source = path.read_text()
        assert "\ndef main(" in source, f"{module}: no main()"
        assert '__name__ == "__main__"' in source, f"{module}: `python -m {module}` would not run main()"
        if module != "ecas.launch":
            assert f'prog="ecas {name}"' in source, f"{module}: its --help should name `ecas {name}`"
