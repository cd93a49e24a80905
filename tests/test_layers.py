"""The import-layers contract: every import inside rlplat points down, and nothing imports in a
circle.

Layers, bottom to top: the shared base (errors, io, cli), scenarios, envs, agents, eval, and the
wiring package experiment, the only code that reads a Hydra config. A module may import its
own layer and those below it. Entry points sit above everything: the ``__main__`` modules, the
command-line module ``rlplat.airsim`` and the package's lazy facade ``rlplat/__init__.py``.
Imports inside functions count too (a lazy import is still a dependency).
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "rlplat"
LAYERS = ("base", "scenarios", "envs", "agents", "eval", "experiment", "entry")
BASE = ("rlplat.errors", "rlplat.io", "rlplat.cli")
ENTRY = ("rlplat", "rlplat.airsim")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> str:
    if module in ENTRY or module.endswith(".__main__"):
        return "entry"
    if module in BASE:
        return "base"
    package = module.split(".")[1]
    if package not in LAYERS:
        raise AssertionError(f"{module}: not in a layer; add it to LAYERS or BASE")
    return package


def rlplat_imports(path: Path) -> set[str]:
    """The rlplat modules ``path`` imports (``from rlplat.x import y``: rlplat.x.y if that is
    a module, else rlplat.x)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("rlplat"))
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("rlplat"):
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                found.add(sub if sub in MODULES else node.module)
    return found


MODULES = {module_name(p): p for p in ROOT.rglob("*.py")}
GRAPH = {name: rlplat_imports(path) for name, path in MODULES.items()}


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_point_down(module):
    own = LAYERS.index(layer(module))
    upward = [m for m in sorted(GRAPH[module]) if LAYERS.index(layer(m)) > own]
    assert not upward, f"{module} ({layer(module)}) imports from a higher layer: {upward}"


def test_no_import_circle():
    # Depth-first search for a back edge among the modules (packages included: importing a
    # submodule runs its package's __init__ first).
    state: dict[str, str] = {}

    def visit(node: str, path: list[str]) -> None:
        state[node] = "open"
        for nxt in sorted(GRAPH.get(node, ())):
            if state.get(nxt) == "open":
                cycle = path[path.index(nxt) :] + [nxt]
                raise AssertionError("import circle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = "done"

    for module in sorted(GRAPH):
        if module not in state:
            visit(module, [module])


def test_envs_know_no_learner_and_no_config():
    for module, imports in GRAPH.items():
        if layer(module) == "envs":
            assert not {m for m in imports if layer(m) in ("agents", "eval", "experiment")}
            assert "hydra" not in MODULES[module].read_text(), module


def test_the_contract_catches_an_upward_import(tmp_path):
    # The checker itself: an envs module importing the wiring layer is refused.
    bad = ROOT / "envs" / "pursuit.py"
    assert layer("rlplat.experiment.factory") == "experiment"
    assert LAYERS.index(layer("rlplat.experiment.factory")) > LAYERS.index(layer(module_name(bad)))
    fake = tmp_path / "fake.py"
    fake.write_text("from rlplat.experiment.factory import build_env\n")
    assert rlplat_imports(fake) == {"rlplat.experiment.factory"}


def test_no_test_module_imports_another():
    # Shared fixtures and helpers live in tests/conftest.py, which pytest provides; a test module
    # importing another (conftest included) would run that module's setup twice.
    tests_dir = Path(__file__).resolve().parent
    names = {p.stem for p in tests_dir.glob("*.py")} | {"tests"}
    for path in tests_dir.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                found = [node.module]
            elif isinstance(node, ast.Import):
                found = [a.name for a in node.names]
            else:
                continue
            assert not {m.split(".")[0] for m in found} & names, (path.name, found)
