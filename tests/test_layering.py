"""The package's layering (docs/architecture.md, "Layers"), read from the source: every module
sits in one layer, imports only from the layers below it (or its own), no import cycle, and the
physics functions stay short.

Every ``import`` counts: at the top, inside functions and under ``if TYPE_CHECKING:`` (an
annotation is a dependency too). Importing ``a.b.c`` also runs the packages ``a.b`` and ``a``, so
those count as well (but not the importer's own packages, which Python has already started)."""

import ast
import pathlib

SRC = pathlib.Path(__file__).resolve().parents[1] / "src"

# Lowest first. A layer may import its own modules and those of the layers listed for it.
LAYERS = {
    "base": ("neuromotor", "neuromotor.errors", "neuromotor.rotations", "neuromotor.rotations_np", "neuromotor.atomic",
             "neuromotor.compiler", "neuromotor.distributed"),
    "model": ("neuromotor.model",),
    "physics": ("neuromotor.physics",),
    "config": ("neuromotor.config",),
    "io": ("neuromotor.io",),
    "viz": ("neuromotor.viz",),
    "studies": ("neuromotor.studies",),
    "cli": ("neuromotor.cli", "neuromotor.__main__"),
}
MAY_IMPORT = {
    "base": set(),
    "model": {"base"},
    "physics": {"base", "model"},
    "config": {"base", "model", "physics"},
    "io": {"base", "model", "physics", "config"},
    "viz": {"base", "model", "io"},  # pictures are drawn from files and arrays, not from the physics
    "studies": {"base", "model", "physics", "config", "io", "viz"},
    "cli": {"base", "model", "physics", "config", "io", "viz", "studies"},
}


def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _ancestors(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _imports(name: str, path: pathlib.Path) -> set[str]:
    """Every neuromotor module ``name`` imports: at the top, inside functions and under
    ``if TYPE_CHECKING:``, with the packages that importing them runs."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:  # relative: from .x import y
                base = package[:len(package) - node.level + 1]
                module = ".".join(base + ([module] if module else []))
            if module.split(".")[0] != "neuromotor":
                continue
            for alias in node.names:
                sub = f"{module}.{alias.name}"
                found.add(sub if sub in MODULES else module)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "neuromotor")
    own = set(_ancestors(name))
    implied = {p for m in found for p in _ancestors(m) if p not in own}
    return {m for m in found | implied if m in MODULES} - {name}


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def layer_of(module: str) -> str | None:
    """The layer of the longest listed name that is ``module`` or a package above it (the package
    root ``neuromotor`` is listed for itself only)."""
    owners = [(len(p), key) for key, names in LAYERS.items() for p in names
              if module == p or (p != "neuromotor" and module.startswith(p + "."))]
    return max(owners)[1] if owners else None


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    return [f"{m} ({layer_of(m)}) -> {d} ({layer_of(d)})" for m, deps in sorted(graph.items())
            for d in sorted(deps) if layer_of(d) != layer_of(m) and layer_of(d) not in MAY_IMPORT[layer_of(m)]]


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if not state.get(nxt):
                cycle = dfs(nxt)
                if cycle:
                    return cycle
        stack.pop()
        state[node] = 2
        return None

    for name in sorted(graph):
        if not state.get(name):
            cycle = dfs(name)
            if cycle:
                return cycle
    return None


def test_every_module_has_a_layer():
    assert [m for m in MODULES if layer_of(m) is None] == []
    assert set(MAY_IMPORT) == set(LAYERS)
    for layer, allowed in MAY_IMPORT.items():  # the layers form one order: no layer allows a higher one
        order = list(LAYERS)
        assert all(order.index(a) < order.index(layer) for a in allowed), layer


def test_no_import_cycle():
    cycle = find_cycle(GRAPH)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_upward_import():
    assert upward_imports(GRAPH) == []


def test_the_package_root_imports_nothing():
    """``neuromotor/__init__.py`` runs before any of its modules, so it imports none of them:
    its public names are loaded on first use (``_API``), and any module may read ``__version__``."""
    assert GRAPH["neuromotor"] == set()


def test_the_checks_see_the_package():
    """Guards the checks above against passing vacuously: the graph holds known edges of every
    kind (top level, inside a function, under ``TYPE_CHECKING``, a package run by a submodule's
    import), and the checks catch a planted upward import and a planted cycle."""
    assert {name for name in MODULES if "." not in name[len("neuromotor."):]} >= {
        f"neuromotor.{m}" for m in ("rotations", "errors", "compiler", "distributed", "model", "physics",
                                    "config", "io", "studies", "viz", "cli")}
    assert "neuromotor.physics.control" in GRAPH["neuromotor.physics.dynamics"]  # top level
    assert "neuromotor.errors" in GRAPH["neuromotor.compiler"]  # inside a function
    assert "neuromotor.studies.simulate" in GRAPH["neuromotor.studies.record"]  # under TYPE_CHECKING
    assert "neuromotor.physics.solvers" in GRAPH["neuromotor.physics.constraints"]  # the package it runs
    assert layer_of("neuromotor.physics.solvers.nullspace") == "physics" and layer_of("neuromotor") == "base"
    planted = {**GRAPH, "neuromotor.model.bvh": GRAPH["neuromotor.model.bvh"] | {"neuromotor.io.runfile"}}
    assert set(upward_imports(planted)) - set(upward_imports(GRAPH)) == {
        "neuromotor.model.bvh (model) -> neuromotor.io.runfile (io)"}
    planted = {**GRAPH, "neuromotor.physics.system": GRAPH["neuromotor.physics.system"] | {"neuromotor.physics.dynamics"}}
    assert find_cycle(planted) is not None


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
