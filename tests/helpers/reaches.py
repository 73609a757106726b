"""The reader of reaches past another library's public API, read statically with `ast`: shared by the rollout seam's
boundary (tests/rollout/test_seam.py) and the backbones' declared reaches into lerobot
(tests/backbones/test_lerobot_reaches.py), so both houses are held to one definition of a reach."""

from __future__ import annotations

import ast
from pathlib import Path

import graftcache

PACKAGE = Path(graftcache.__file__).parent
#: the simulator's libraries: an attribute of theirs is written only by the seam
SIMULATOR = ("lerobot", "libero", "robosuite", "mujoco")
#: the standard library's private names graftcache uses: argparse's action classes (type hints), os._exit
STANDARD = {"_SubParsersAction", "_ActionsContainer", "_exit"}


def private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def package_trees() -> dict[Path, ast.Module]:
    """Every module of graftcache, parsed."""
    return {path: ast.parse(path.read_text(), str(path)) for path in sorted(PACKAGE.rglob("*.py"))}


def own_names(trees: list[ast.Module]) -> set[str]:
    """The private names graftcache defines: its functions and classes, its module-level names, its attributes set
    on self or cls."""
    own = set()
    for node in (n for tree in trees for n in ast.walk(tree)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            own.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            own.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and \
                isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
            own.add(node.attr)
    return {name for name in own if private(name)}


def _simulator_modules(tree: ast.Module) -> set[str]:
    """The local names bound to the simulator's libraries' modules or objects by `tree`'s imports."""
    bound = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            module = node.module if isinstance(node, ast.ImportFrom) else None
            for alias in node.names:
                source = module or alias.name
                if source.split(".")[0] in SIMULATOR:
                    bound.add(alias.asname or alias.name.split(".")[0])
    return bound


def reaches(tree: ast.Module, own: set[str], written: set[str],
            forbidden: set[str]) -> list[tuple[int, str, str]]:
    """(line, name reached, how) for each reach past another library's public API in `tree`: a private name
    imported from outside graftcache, a private attribute read or written on anything but self or cls that graftcache
    does not define (or one of `forbidden`, names known to be another library's, whoever defines them), an attribute
    written on a simulator library's module or object, or of a name in `written` (what the seam writes on the
    simulator's objects), by assignment or setattr."""
    found, modules = [], _simulator_modules(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and not (node.module or "").startswith("graftcache") and not node.level:
            found += [(node.lineno, a.name, f"from {node.module} import {a.name}") for a in node.names
                      if private(a.name) and a.name not in STANDARD]
        elif isinstance(node, ast.Attribute):
            on = ast.unparse(node.value)
            stored = isinstance(node.ctx, ast.Store | ast.Del)
            if private(node.attr) and on not in ("self", "cls") and (node.attr in forbidden or
                                                                    node.attr not in own | STANDARD):
                found.append((node.lineno, node.attr, f"{on}.{node.attr}"))
            elif stored and (node.attr in written or on.split(".")[0] in modules):
                found.append((node.lineno, node.attr, f"{on}.{node.attr} ="))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("setattr", "delattr"):
            name = node.args[1] if len(node.args) > 1 else None
            if isinstance(name, ast.Constant) and (private(name.value) or name.value in written):
                found.append((node.lineno, name.value, ast.unparse(node)))
    return found
