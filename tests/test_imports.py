"""The package's import graph follows the data: no cycles, stage 1 never imports stage 2, the library never imports
its command line (graftcache/cli/, above it) nor the developer tools beside it (devtools/: what tests and benchmarks
build).

Read statically with `ast` (module-level and function-level imports alike, `TYPE_CHECKING` blocks
included), so a cycle hidden behind a lazy import fails here too, not only at whatever import order
happens to break it at runtime.
"""

from __future__ import annotations

import ast
from pathlib import Path

import graftcache

PACKAGE = Path(graftcache.__file__).parent
#: Stage 1 (dataset -> features in the cache) and stage 2 (cache -> fits -> reports), by module prefix.
STAGE_1 = ("datasets", "encoders", "store", "extract", "pooling")
STAGE_2 = ("backbones", "fit", "pretrain", "analysis", "report", "sweep", "recipe", "export", "rollout")


def _modules() -> dict[str, tuple[Path, bool]]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = ["graftcache", *path.relative_to(PACKAGE).with_suffix("").parts]
        is_package = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return out


def import_graph() -> dict[str, set[str]]:
    """module -> the graftcache modules it imports anywhere in its body (an imported name that is a
    submodule counts as that submodule; importing a submodule does not count its package)."""
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, (path, is_package) in modules.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = module.split(".")[: len(module.split(".")) - (node.level - (1 if is_package else 0))]
                    base = ".".join([*anchor, *([node.module] if node.module else [])])
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target.startswith("graftcache") and target != module:
                    graph[module].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def devtools_imports(source: str) -> list[str]:
    """What a module's source takes from devtools: imports anywhere in it, and "devtools.x:name" strings (the
    lazy registries' import strings, graftcache.lazy), which would import it at run time."""
    def ours(name: str | None) -> bool:
        return (name or "").partition(".")[0] == "devtools"

    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if ours(a.name)]
        elif isinstance(node, ast.ImportFrom) and not node.level and ours(node.module):
            found.append(node.module)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith(
                ("devtools.", "devtools:")):
            found.append(node.value)
    return found


def _in(module: str, stage: tuple[str, ...]) -> bool:
    rest = module.removeprefix("graftcache.")
    return any(rest == s or rest.startswith(f"{s}.") for s in stage)


def test_the_graph_reader_sees_a_cycle_and_every_kind_of_import() -> None:
    graph = import_graph()
    # module-level, function-level (lazy) and `from package import submodule` imports; import strings are not
    assert "graftcache.store" in graph["graftcache.extract"]
    assert "graftcache.backbones.tower_encoder" not in graph["graftcache.encoders.catalog"]  # named by string only
    assert "graftcache.fit.lookup" in graph["graftcache.cli.extract"]  # imported inside a function
    assert "graftcache.encoders.catalog" in graph["graftcache.encoders"]  # `from graftcache.encoders import catalog`
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles() -> None:
    found = cycles(import_graph())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_stage_1_never_imports_stage_2() -> None:
    graph = import_graph()
    assert any(_in(m, STAGE_1) for m in graph) and any(_in(m, STAGE_2) for m in graph)
    wrong = sorted(f"{m} -> {t}" for m, targets in graph.items() if _in(m, STAGE_1)
                   for t in targets if _in(t, STAGE_2))
    assert not wrong, "stage 1 imports stage 2: " + ", ".join(wrong)


def test_the_library_never_imports_the_cli() -> None:
    """Issue 41, item 3: nothing under graftcache/ outside graftcache/cli/ imports graftcache.cli (but the entry point
    `python -m graftcache`): the library never parses its own command lines back (an export read a row's cell from
    the command line it recorded), it reads what rows and run folders record."""
    graph = import_graph()
    assert "graftcache.cli" in graph["graftcache.__main__"]  # the check sees such an import
    wrong = sorted(f"{m} -> {t}" for m, targets in graph.items() if not _in(m, ("cli", "__main__"))
                   for t in targets if _in(t, ("cli",)))
    assert not wrong, "the library imports the CLI: " + ", ".join(wrong)


def test_the_library_never_imports_devtools() -> None:
    seen = devtools_imports("import devtools.tile\nfrom devtools.released import BUILDERS\n"
                            "def f():\n    from devtools import tile\nX = 'devtools.tile:tile'\nY = 'devtools'\n")
    assert seen == ["devtools.tile", "devtools.released", "devtools", "devtools.tile:tile"]
    wrong = {m: found for m, (path, _) in _modules().items() if (found := devtools_imports(path.read_text()))}
    assert not wrong, f"graftcache imports devtools: {wrong}"
