"""The package's layering (docs/architecture.md), read from the source: no import cycle, the
physics never reaches up into studies, files or pictures, and its functions stay short."""

import ast
import pathlib

import pytest

SRC = pathlib.Path(__file__).resolve().parents[1] / "src"


def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _imports(path: pathlib.Path) -> set[str]:
    """Every neuromotor module ``path`` imports, at the top or inside functions, except under
    ``if TYPE_CHECKING:`` (annotations only)."""
    found = set()

    def visit(node):
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            return
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("neuromotor"):
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                found.add(sub if sub in MODULES else node.module)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("neuromotor"))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text()))
    return {m for m in found if m in MODULES}


GRAPH = {name: _imports(path) - {name} for name, path in MODULES.items()}


def _package_edge(a: str, b: str) -> bool:
    """A package's ``__init__`` re-exporting its own submodules is not a dependency cycle."""
    return b.startswith(a + ".")


def test_no_import_cycle():
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(node):
        state[node] = 1
        stack.append(node)
        for nxt in GRAPH[node]:
            if _package_edge(node, nxt):
                continue
            if state.get(nxt) == 1:
                pytest.fail("import cycle: " + " -> ".join(stack[stack.index(nxt):] + [nxt]))
            if not state.get(nxt):
                dfs(nxt)
        stack.pop()
        state[node] = 2

    for name in GRAPH:
        if not state.get(name):
            dfs(name)


@pytest.mark.parametrize("layer, forbidden", [
    ("neuromotor.model", ("neuromotor.physics", "neuromotor.studies", "neuromotor.viz", "neuromotor.cli",
                          "neuromotor.config")),
    ("neuromotor.physics", ("neuromotor.studies", "neuromotor.io", "neuromotor.viz", "neuromotor.cli",
                            "neuromotor.config")),
    ("neuromotor.studies", ("neuromotor.cli",)),
    ("neuromotor.viz", ("neuromotor.physics", "neuromotor.studies", "neuromotor.cli")),
])
def test_lower_layers_do_not_import_higher_ones(layer, forbidden):
    bad = [(m, d) for m, deps in GRAPH.items() if m.startswith(layer) for d in deps
           if d.startswith(forbidden)]
    assert not bad, bad


def test_physics_functions_stay_short():
    long = []
    for name, path in MODULES.items():
        if not name.startswith("neuromotor.physics"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > 60:
                    long.append(f"{path.name}:{node.lineno} {node.name} ({length} lines)")
    assert not long, long


def test_the_checks_see_the_package():
    """Guards the checks above against passing vacuously."""
    assert {"neuromotor.physics.dynamics", "neuromotor.physics.solvers.nullspace",
            "neuromotor.studies.simulate"} <= set(GRAPH)
    assert "neuromotor.physics.control" in GRAPH["neuromotor.physics.dynamics"]
