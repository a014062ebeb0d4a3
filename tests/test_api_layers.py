"""The import graph: library modules below the commands, and no import cycle.

Every `import` in src/disco_cli is read with `ast` (those inside functions too):
no module outside `commands/` and `cli.py` may import either, a package imports
nothing of a higher layer (`LAYERS`), the graph of module-level imports between
library modules must have no cycle, and an import inside a function says why it is
not at the top (`# deferred: ...`).
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parent.parent / "src" / "disco_cli"


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, top_level_only: bool) -> set[str]:
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            # `from disco_cli import maps` imports the module disco_cli.maps
            found |= {f"{node.module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.If) and top_level_only:  # `if TYPE_CHECKING:` is no import
            continue
    return {m for m in found if m == "disco_cli" or m.startswith("disco_cli.")}


def modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PKG.rglob("*.py")}


def _is_cli(name: str) -> bool:
    return name in ("disco_cli.cli",) or name.startswith("disco_cli.commands")


def test_library_never_imports_the_commands() -> None:
    bad = []
    for name, path in modules().items():
        if _is_cli(name):
            continue
        bad += [f"{name} imports {m}" for m in _imports(path, False) if _is_cli(m)]
    assert not bad, bad


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Cycles found by a depth-first search (each as the path that closes it)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    cycles: list[list[str]] = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt) :] + [nxt])
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    return cycles


def test_find_cycles_finds_one() -> None:
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []


def test_no_import_cycle_at_module_level() -> None:
    mods = modules()
    graph = {
        name: {m for m in _imports(path, True) if m in mods and m != name}
        for name, path in mods.items()
    }
    assert sum(map(len, graph.values())) > 20  # the graph was read
    assert not find_cycles(graph)


def test_the_api_modules_exist_and_commands_stay_thin() -> None:
    for name in ("maps/facade", "query/localize", "query/loop_detector"):
        assert (PKG / f"{name}.py").is_file()
    # Argument parsing, reading inputs, calling the library, writing rows: the
    # pipelines live in library modules, so each of these stays well under 150 lines.
    for command in ("query", "loops", "build_db", "evaluate", "eval_loops"):
        lines = (PKG / "commands" / f"{command}.py").read_text().count("\n")
        assert lines <= 150, f"commands/{command}.py has {lines} lines"


def test_layout_by_stage() -> None:
    # Issue 32: folders show the data flow, the package's top level holds only the
    # entry points, and no module grows past 700 lines.
    top = sorted(p.name for p in PKG.glob("*.py"))
    assert top == ["__init__.py", "cli.py", "errors.py"], top
    stages = {
        "io",
        "embedding",
        "maps",
        "query",
        "model",
        "training",
        "evaluation",
        "commands",
        "service",
    }
    assert stages <= {p.name for p in PKG.iterdir() if (p / "__init__.py").is_file()}
    long = {
        str(p.relative_to(PKG)): n
        for p in PKG.rglob("*.py")
        if (n := p.read_text().count("\n")) > 700
    }
    assert not long, long


# The packages in layers, lowest first: a module imports only from its own layer and the
# layers below it (at module level or deferred). Issue 41: the embedding stage (scans to
# signatures) sits above `model` and below `maps` and `query`, which hand it their scans.
LAYERS = [
    {"errors", "runtime"},
    {"io"},
    {"model"},
    {"embedding"},
    {"maps", "query"},
    {"graph", "simulator", "training"},
    {"evaluation", "service"},
    {"commands", "cli"},
]

# The imports that go up a layer today, each by name, so that no new one slips in.
UPWARD = {
    ("disco_cli.io.loop_export", "disco_cli.query.loop_detector"),
    ("disco_cli.io.loop_export", "disco_cli.query.relative_pose"),
    ("disco_cli.io.output_paths", "disco_cli.maps.milvus_address"),
    ("disco_cli.model.disco", "disco_cli.query.query_policy"),
    ("disco_cli.model.interface", "disco_cli.query.query_policy"),
    ("disco_cli.model.scancontext", "disco_cli.query.query_policy"),
    ("disco_cli.model.spectral", "disco_cli.query.query_policy"),
}


def upward_imports(imports: dict[str, set[str]], layers: list[set[str]]) -> list[tuple[str, str]]:
    """The (module, imported) pairs whose imported module's package is in a higher
    layer than the module's own; a package in no layer is a `KeyError`."""
    rank = {package: i for i, layer in enumerate(layers) for package in layer}

    def package(module: str) -> str:
        return module.split(".")[1]

    return sorted(
        (name, m)
        for name, found in imports.items()
        for m in found
        if rank[package(m)] > rank[package(name)]
    )


def test_upward_imports_are_found() -> None:
    layers = [{"io"}, {"model"}, {"embedding"}, {"maps", "query"}]
    imports = {
        "disco_cli.embedding.load": {"disco_cli.model.bev", "disco_cli.io.readers"},
        "disco_cli.embedding.batches": {"disco_cli.embedding.load", "disco_cli.maps.x"},
        "disco_cli.model.bev": {"disco_cli.embedding.load"},
        "disco_cli.maps.x": {"disco_cli.query.y"},
        "disco_cli.query.y": {"disco_cli.maps.x", "disco_cli.embedding.batches"},
    }
    assert upward_imports(imports, layers) == [
        ("disco_cli.embedding.batches", "disco_cli.maps.x"),
        ("disco_cli.model.bev", "disco_cli.embedding.load"),
    ]


def test_packages_import_only_their_layer_and_those_below() -> None:
    mods = modules()
    library = {name: path for name, path in mods.items() if name != "disco_cli"}
    packages = {name.split(".")[1] for name in library}
    placed = set().union(*LAYERS)
    assert "embedding" in packages and packages <= placed, packages - placed
    # The package's top (`disco_cli`) is the entry point and imports lazily; the
    # compiled core is no Python module.
    imports = {
        name: {m for m in _imports(path, False) if m in library} for name, path in library.items()
    }
    # The embedding stage really is between model and the map: it voxelizes with model/
    # and maps/ and query/ reach it.
    embedding_uses = {m for name, found in imports.items() for m in found if ".embedding." in m}
    assert any(".model." in m for m in imports["disco_cli.embedding.load"])
    assert {"maps", "query"} <= {
        name.split(".")[1] for name, found in imports.items() if found & embedding_uses
    }
    up = set(upward_imports(imports, LAYERS))
    assert not up - UPWARD, f"imports of a higher layer: {sorted(up - UPWARD)}"
    assert not UPWARD - up, f"gone, strike them from UPWARD: {sorted(UPWARD - up)}"


def undeclared_deferred_imports(source: str) -> list[int]:
    """Lines of the imports inside functions that do not say why they are deferred.

    An import inside a function needs `# deferred:` on one of its own lines or in the
    comment lines directly above it. A run of imports (statements next to each other in
    one block, blank lines allowed) shares the comment of its first import.
    """
    lines = source.splitlines()
    bad: list[int] = []

    def commented(node: ast.stmt) -> bool:
        own = lines[node.lineno - 1 : node.end_lineno]
        above = []
        for text in reversed(lines[: node.lineno - 1]):
            if not text.strip().startswith("#"):
                break
            above.append(text)
        return any("# deferred:" in text for text in own + above)

    def visit(node: ast.AST, in_function: bool) -> None:
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            block = getattr(node, field, None)
            if not isinstance(block, list):
                continue
            run_ok = None  # whether the run of imports this statement continues is declared
            for stmt in block:
                if isinstance(stmt, (ast.Import, ast.ImportFrom)) and in_function:
                    run_ok = commented(stmt) or bool(run_ok)
                    if not run_ok:
                        bad.append(stmt.lineno)
                    continue
                run_ok = None
                inner = in_function or isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef))
                visit(stmt, inner)

    visit(ast.parse(source), False)
    return bad


def test_the_deferred_check_finds_undeclared_imports() -> None:
    source = "\n".join(
        [
            "import os",  # 1: module level, needs nothing
            "def f():",
            "    import json",  # 3: no comment
            "    # deferred: torch costs 0.5 s at start-up",
            "    import torch",  # 5: the comment above
            "",
            "    from disco_cli import maps",  # 7: same run as line 5
            "    x = 1",
            "    import scipy",  # 9: code above ends the run
            "    # a comment that gives no reason",
            "    import faiss",  # 11
            "    import numpy  # deferred: numpy costs 0.1 s",  # 12: its own line
            "    try:",
            "        import rich",  # 14: a new block
            "    except ImportError:",
            "        pass",
            "    class A:",
            "        def g(self):",
            "            from x import (",
            "                y,  # deferred: optional extra",  # 19-21: on one of its lines
            "            )",
            "            import z",  # 22: same run
            "    def h():",
            "        import rich",  # 24: nested function
        ]
    )
    assert undeclared_deferred_imports(source) == [3, 9, 11, 14, 24]


def test_imports_inside_functions_say_why_they_are_deferred() -> None:
    bad, checked = [], 0
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG).as_posix()
        checked += 1
        bad += [f"{rel}:{line}" for line in undeclared_deferred_imports(path.read_text())]
    assert checked > 50  # the package was read
    assert not bad, f"imports inside functions without a `# deferred:` reason: {bad}"
