"""The docs cite only code that exists: every path, dotted name and contract member in README.md, data/README.md
and every page under docs/ is looked up, so a doc that drifts fails here.

The citation convention (stated at the top of docs/ARCHITECTURE.md): paths from the repository root,
Python objects as dotted names from the package, and contract blocks headed `graftcache.x.Class ...:`
whose indented lines name that class's members.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import io
import re
import textwrap
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: the reference pages README.md sends readers to (README.md, "Read on")
PAGES = tuple(sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md")))
DOCS = ("README.md", "data/README.md", *PAGES)
README_LINES = 150
# the repository's top-level folders: a citation starting with one of them is a path that must exist
TOP_DIRS = (".ci", "benchmarks", "cli", "data", "docs", "graftcache", "notebooks", "scripts", "tests")
FILE_SUFFIXES = ("py", "md", "html", "toml", "json", "ipynb", "sh", "parquet", "png", "safetensors", "txt")

PATH = re.compile(r"(?<![\w./~$<>-])((?:" + "|".join(map(re.escape, TOP_DIRS)) + r")/[\w./-]*)")
DOTTED = re.compile(r"(?<![\w./-])graftcache(?:\.[A-Za-z_]\w*)+")
BACKTICKED = re.compile(r"`([^`\n]+)`")
HEADER = re.compile(r"^( {4,})(graftcache(?:\.\w+)+)\b[^:#]*:\s*$")
MEMBER = re.compile(r"^\s*(?:def\s+)?([A-Za-z_]\w*)\s*[:(]")


def _module_names() -> set[str]:
    return {p.stem for p in (ROOT / "graftcache").iterdir() if p.suffix == ".py" or (p / "__init__.py").is_file()}


def _import_prefix(dotted: str) -> tuple[object, list[str]]:
    """The longest importable module prefix of a dotted name, and the attribute names after it."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        name = ".".join(parts[:i])
        try:
            return importlib.import_module(name), parts[i:]
        except ModuleNotFoundError as e:
            if e.name is None or not (name + ".").startswith(e.name + "."):
                raise  # the module exists but one of its own imports is missing: a real error
    raise AssertionError(f"no importable prefix in {dotted}")


def _instance_attributes(cls: type) -> set[str]:
    """Names assigned as `self.<name> = ...` in the methods of cls and its graftcache bases."""
    names: set[str] = set()
    for klass in inspect.getmro(cls):
        if not klass.__module__.startswith("graftcache"):
            continue
        for node in ast.walk(ast.parse(textwrap.dedent(inspect.getsource(klass)))):
            targets = node.targets if isinstance(node, ast.Assign) else \
                [node.target] if isinstance(node, (ast.AnnAssign, ast.AugAssign)) else []
            for target in targets:
                names |= {n.attr for n in ast.walk(target) if isinstance(n, ast.Attribute)
                          and isinstance(n.value, ast.Name) and n.value.id == "self"}
    return names


def _has_member(obj: object, name: str) -> bool:
    """An attribute, or for a class also a dataclass field, an annotation or an attribute set on self."""
    if hasattr(obj, name):
        return True
    if not inspect.isclass(obj):
        return False
    if dataclasses.is_dataclass(obj) and name in {f.name for f in dataclasses.fields(obj)}:
        return True
    annotated = set().union(*(getattr(k, "__annotations__", {}) for k in inspect.getmro(obj)))
    return name in annotated or name in _instance_attributes(obj)


def _resolve(dotted: str) -> object:
    obj, attrs = _import_prefix(dotted)
    for attr in attrs:
        if not _has_member(obj, attr):
            raise AttributeError(attr)
        obj = getattr(obj, attr, None)
    return obj


def _module_map_files(text: str) -> list[str]:
    """Bare file names in the module map, as paths under the folder their line (or the line above) names:
    `graftcache/fit/   run.py (...), data.py` cites graftcache/fit/run.py and graftcache/fit/data.py."""
    section = text.split("## Module map", 1)[1].split("\n## ", 1)[0] if "## Module map" in text else ""
    files, folder = [], None
    for line in section.splitlines():
        head = re.match(r"^ {4}(\S+/)\s", line)
        if head:
            folder = head.group(1)
        elif not line.startswith(" " * 5):
            folder = None
        if folder:
            files += [folder + name for name in re.findall(r"(?<![\w/.])(\w+\.py)\b", line)]
    return files


def problems(text: str) -> list[str]:
    """Every citation in `text` that does not resolve, one line each (empty when the doc is true)."""
    out = []
    for path in sorted({m.rstrip(".,") for m in PATH.findall(text)} | set(_module_map_files(text))):
        if not (ROOT / path).exists():
            out.append(f"path {path} does not exist")
    for dotted in sorted(set(DOTTED.findall(text))):
        try:
            _resolve(dotted)
        except (AttributeError, AssertionError) as e:
            out.append(f"{dotted}: no {e}")
    modules = _module_names()
    for span in sorted(set(BACKTICKED.findall(text))):
        short = re.match(r"^(\w+)\.(\w+)", span)
        if short and short.group(1) in modules and short.group(2) not in FILE_SUFFIXES:
            out.append(f"`{span}`: cite objects from the package root (graftcache.{span})")
        if re.search(r"\.py:\w", span):
            out.append(f"`{span}`: cite objects as dotted names, not file.py:symbol")
    lines = text.splitlines()
    for i, line in enumerate(lines):
        head = HEADER.match(line)
        if not head:
            continue
        owner = _resolve(head.group(2))
        for body in lines[i + 1:]:
            if body.strip() and len(body) - len(body.lstrip()) <= len(head.group(1)):
                break
            for part in body.split("#", 1)[0].split(";"):
                member = MEMBER.match(part)
                if member and not _has_member(owner, member.group(1)):
                    out.append(f"{head.group(2)} has no member {member.group(1)}")
    return out


def test_the_readme_is_short_and_sends_readers_to_every_page() -> None:
    """README.md is read to the end (at most README_LINES lines) and the reference lives under docs/: its "Read on"
    list names every page there, and every page it names exists (test_every_citation_resolves)."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= README_LINES
    read_on = readme.split("## Read on", 1)[1]
    assert [page for page in PAGES if f"`{page}`" not in read_on] == []


def test_top_level_folders_exist() -> None:
    assert [d for d in TOP_DIRS if not (ROOT / d).is_dir()] == []


@pytest.mark.parametrize("doc", DOCS)
def test_every_citation_resolves(doc: str) -> None:
    assert problems((ROOT / doc).read_text(encoding="utf-8")) == []


def test_architecture_cites_enough_to_be_checked() -> None:
    """The patterns find the citations the doc is made of (a pattern that matched nothing would pass)."""
    text = (ROOT / "docs/ARCHITECTURE.md").read_text(encoding="utf-8")
    assert len(set(DOTTED.findall(text))) >= 40
    assert len(set(PATH.findall(text))) >= 25
    assert {"graftcache/fit/run.py", "graftcache/report/render.py"} <= set(_module_map_files(text))
    headers = [m.group(2) for line in text.splitlines() if (m := HEADER.match(line))]
    assert "graftcache.encoders.EncoderSpec" in headers and len(headers) >= 6


def test_drift_is_caught() -> None:
    """Each way a doc drifted before (a renamed function, a method that never existed, a field the dict
    does not have, a file that moved, a short-form citation) is reported."""
    drifted = """
See `graftcache.results.append_rows` and `graftcache/fit/nowhere.py`, `store.compare_identity` and
`extract.py:extract`.

## Module map

    graftcache/fit/                   run.py, gone.py

## Contracts

    graftcache.encoders.Encoder:
        spec: EncoderSpec
        def extra_outputs(...)      # native towers only
    graftcache.encoders.EncoderSpec (frozen dataclass):
        name: str; wheel: str
"""
    assert problems(drifted) == [
        "path graftcache/fit/gone.py does not exist",
        "path graftcache/fit/nowhere.py does not exist",
        "graftcache.results.append_rows: no append_rows",
        "`extract.py:extract`: cite objects as dotted names, not file.py:symbol",
        "`store.compare_identity`: cite objects from the package root (graftcache.store.compare_identity)",
        "graftcache.encoders.Encoder has no member extra_outputs",
        "graftcache.encoders.EncoderSpec has no member wheel",
    ]


# ------------------------------------------------------------------------------------------------- the glossary
#: where the code lives whose names the glossary governs
CODE_DIRS = ("graftcache", "devtools", "benchmarks", "tests")


def glossary(text: str) -> dict[str, tuple[list[str], list[str]]]:
    """word -> (dotted names in its code column, retired names), from the `## Glossary` table; a retired module
    is written `module NAME`."""
    section = text.split("## Glossary", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))] if line.startswith("|") else []
        if len(cells) == 4 and cells[0] not in ("word", "---"):
            cited = re.findall(r"`(graftcache\.[\w.]+)`", cells[2])
            rows[cells[0]] = (cited, re.findall(r"module `?(\w+)`?|`(\w+)`", cells[3]))
    return {word: (cited, [f"module {m}" if m else name for m, name in retired])
            for word, (cited, retired) in rows.items()}


def names_in(source: str, module: str) -> set[str]:
    """Every name a Python file defines or uses: its module path's parts, classes, functions, arguments, names,
    attributes, import paths and aliases, keyword arguments, and the parts of "graftcache.x:y" import strings."""
    names = {f"module {part}" for part in module.split(".")}
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
        elif isinstance(node, ast.Name):
            names.add(node.id)
        elif isinstance(node, ast.Attribute):
            names.add(node.attr)
        elif isinstance(node, ast.keyword) and node.arg:
            names.add(node.arg)
        elif isinstance(node, ast.alias):
            names |= {node.asname or "", *(f"module {p}" for p in node.name.split("."))}
            names.add(node.name.rsplit(".", 1)[-1])
        elif isinstance(node, ast.ImportFrom) and node.module:
            names |= {f"module {p}" for p in node.module.split(".")}
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            for path in re.findall(r"graftcache(?:\.\w+)+(?::\w+)?", node.value):
                dotted, _, attr = path.partition(":")
                names |= {f"module {p}" for p in dotted.split(".")[1:]} | {attr}
    return names - {""}


def retired_in_code(retired: set[str]) -> list[str]:
    """'path: name' for every retired name the code still uses."""
    out = []
    for folder in CODE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path == Path(__file__).resolve():
                continue  # this file's own sample of retired names (the test below)
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            out += [f"{path.relative_to(ROOT)}: {n}" for n in sorted(names_in(path.read_text(), module) & retired)]
    return out


def test_the_glossary_names_code_that_exists_and_no_retired_name_is_used() -> None:
    rows = glossary((ROOT / "docs/ARCHITECTURE.md").read_text(encoding="utf-8"))
    assert {"native", "cell", "grid", "run", "pool", "checkpoint", "shard", "construct"} <= set(rows)
    assert all(cited for cited, _ in rows.values())  # every word points at code (resolved by the citation test)
    retired = {name for _, names in rows.values() for name in names}
    assert {"BackbonePool", "NativeEncoder", "module recompute", "module lean", "module draws", "plan_passes",
            "looks_planned", "module backbone_table"} <= retired
    assert retired_in_code(retired) == []


def test_a_retired_name_is_found_wherever_the_code_uses_it() -> None:
    source = ('from graftcache.backbones.pool import BackbonePool\n'
              'def f(can_checkpoint): return x.checkpoint_patches, g(_check_grid=1)\n'
              'BUILD = "graftcache.backbones.native:build_native"\n')
    found = names_in(source, "graftcache.backbones.recompute")
    assert {"module pool", "BackbonePool", "can_checkpoint", "checkpoint_patches", "_check_grid", "module native",
            "build_native", "module recompute"} <= found
    assert "module lean" not in found  # module names match whole, not as prefixes
    assert not names_in("pool_grid(x)", "graftcache.pooling") & {"module pool", "BackbonePool"}



# ------------------------------------------------------------------------------------------- the glossary's rules
#: where the glossary's forbidden patterns and dotted names in prose are looked for (besides DOCS_SEARCHED)
PROSE_DIRS = ("graftcache",)
#: the docs whose text the forbidden patterns search (their `## Glossary` section, which defines the words, aside)
DOCS_SEARCHED = ("README.md", *PAGES)


def glossary_rules(text: str) -> dict[str, list[re.Pattern]]:
    r"""word -> its forbidden patterns, from the table under `## Glossary` whose header is `| word | forbidden | ...`
    (a `|` inside a pattern is written `\|`, as markdown tables need)."""
    section = text.split("## Glossary", 1)[1].split("\n## ", 1)[0]
    table = section.split("| word | forbidden |", 1)[1]
    rules: dict[str, list[re.Pattern]] = {}
    for line in table.splitlines()[2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]
        rules.setdefault(cells[0], []).append(re.compile(cells[1].strip("`").replace(r"\|", "|")))
    return rules


def _docstring_lines(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, text) of every line of the module's, classes' and functions' docstrings."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) \
                    and isinstance(first.value.value, str):
                out += [(first.lineno + i, line) for i, line in enumerate(first.value.value.splitlines())]
    return out


def prose_of(source: str) -> list[tuple[int, str]]:
    """(line, text) of a Python file's docstrings and comments: what it says in words (stored strings, messages
    and help texts are values, not names, and are not searched)."""
    comments = [(t.start[0], t.string) for t in tokenize.generate_tokens(io.StringIO(source).readline)
                if t.type == tokenize.COMMENT]
    return sorted(comments + _docstring_lines(ast.parse(source)))


def identifiers_of(source: str) -> list[tuple[int, str]]:
    """(line, name) of every name a Python file defines or uses: classes, functions, arguments, names,
    attributes, keyword arguments, imported names and aliases."""
    out = []
    for node in ast.walk(ast.parse(source)):
        name = node.name if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) else \
            node.arg if isinstance(node, (ast.arg, ast.keyword)) else node.id if isinstance(node, ast.Name) else \
            node.attr if isinstance(node, ast.Attribute) else \
            (node.asname or node.name.rsplit(".", 1)[-1]) if isinstance(node, ast.alias) else None
        if name:
            out.append((node.lineno if hasattr(node, "lineno") else 0, name))
    return out


def searched_text() -> list[tuple[str, str]]:
    """('file:line', text) of everything the glossary's rules govern: identifiers, docstrings and comments under
    PROSE_DIRS, and the lines of DOCS_SEARCHED outside their glossary."""
    out = []
    for folder in PROSE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            source, where = path.read_text(encoding="utf-8"), path.relative_to(ROOT)
            out += [(f"{where}:{line}", text) for line, text in identifiers_of(source) + prose_of(source)]
    for doc in DOCS_SEARCHED:
        text = (ROOT / doc).read_text(encoding="utf-8")
        glossary_lines = range(0)
        if "## Glossary" in text:
            start = text[:text.index("## Glossary")].count("\n")
            glossary_lines = range(start, start + text.split("## Glossary", 1)[1].split("\n## ", 1)[0].count("\n"))
        out += [(f"{doc}:{i + 1}", line) for i, line in enumerate(text.splitlines()) if i not in glossary_lines]
    return out


def rule_breaches(rules: dict[str, list[re.Pattern]], searched: list[tuple[str, str]]) -> list[str]:
    """'file:line: word: the match' for every match of a word's forbidden pattern."""
    return [f"{where}: {word}: {m.group(0)!r}" for word, patterns in rules.items() for pattern in patterns
            for where, text in searched if (m := pattern.search(text))]


def test_no_word_of_the_glossary_is_used_for_another_idea() -> None:
    rules = glossary_rules((ROOT / "docs/ARCHITECTURE.md").read_text(encoding="utf-8"))
    assert {"activation checkpointing", "recompute", "grid", "shard", "loss per sample", "plan", "objective",
            "table", "scene", "team"} <= set(rules)
    assert rule_breaches(rules, searched_text()) == []


def test_each_overloaded_use_breaks_a_rule() -> None:
    """Each overloaded use the glossary retired (graftcache issue 41) matches its word's pattern, and the words
    in their own sense match none."""
    rules = glossary_rules((ROOT / "docs/ARCHITECTURE.md").read_text(encoding="utf-8"))
    overloaded = {
        "activation checkpointing": ["CHECKPOINTING_MODES", "checkpointing", "Checkpointing is graftcache's switch"],
        "recompute": ["The step measured decides `--activation-checkpointing auto`", "activation checkpointing mode"],
        "grid": ["False: a sweep sets it from its grid", "every field not set by the sweep's grid"],
        "shard": ["frames per Zarr shard", "zarr writes each shard file once", "safetensors (single or sharded)"],
        "spec": ["TinySpec"],
        "loss per sample": ["per_sample_loss"],
        "plan": ["plan_passes", "plan_copies", "plan_blocks", "_plan", "_plan_windows", "looks_planned", "planned",
                 "One planned episode", "the selected cells' episodes planned", "started before planning",
                 "a rerun of the same command plans the same episodes", "the team of this process plans",
                 "with a team, it only plans", "builds its own, to plan", "The driver plans every request",
                 "Planned before passes are formed", "Planning a fit", "workers start before the rollout plans"],
        "objective": ["X-VLA's objective is not lerobot's velocity flow", "None: no flow time (a token objective)",
                      "pi0-FAST's own objective", "It mixes in its objective", "# ----------------------- objectives",
                      "each adds its construction, processors and objective",
                      "one lerobot VLA policy, frozen, with the graft surgery and the objectives"],
        "table": ["graftcache.backbone_table.BACKBONES", "the encoder catalog, the backbone table",
                  "over the recipe's [fit] table", "a recipe's `[executor]` table", "A settings table as overrides",
                  "applied on a recipe's tables", "A frozen dataclass from a TOML table",
                  "the table of what trains", "the whole table the first time", "the variant table"],
        "scene": ["scene", "scenes", "feeds the wrist view into the scene slot", "MuJoCo's scene compiler",
                  "hf-libero builds a scene inside"],
        "team": ["a worker pool", "the process pool", "a pool of simulators", "actor_pool"],
    }
    for word, uses in overloaded.items():
        assert [u for u in uses if not rule_breaches({word: rules[word]}, [("x:1", u)])] == [], word
    proper = ["ActivationCheckpointing", "activation checkpointing of the frozen LM", "gradient_checkpointing_enable",
              "token grid", "extract --shard i/N", "the last shard to finish", "BackboneSpec.loss_per_sample",
              "a block file per array",
              "the cell's plan", "Plan.pass_key", "graftcache.fit.plan.Planned", "Planned", "PLANS", "recompute plan",
              "the recompute plans off, mlp, on", "set_recompute_plan", "recompute_plan_patches", "RECOMPUTE_PLANS",
              "a planar offset", "the requests' plans", "The plans this backbone has, least recompute first",
              "the flow objective minimises the policy loss", "its objective (fit/objectives.py)",
              "the align objective", "the request's objective", "cells whose objective takes steps",
              "A fit's objective", "OBJECTIVES", "the results table", "the rollouts table", "report/tables.py",
              "a report table", "the low-dim table", "pq.read_table", "suite_index_table",
              "No `native` rows in the table", "the recipe's [fit] section",
              "the scene of init state k", "the same scene, perturbation and step limit", "perturbed scenes",
              "the third-person slot", "task_env", "the team of one", "pool_grid", "the pool-4x4 control"]
    assert rule_breaches(rules, [("x:1", u) for u in proper]) == []


def dotted_in_prose() -> list[tuple[str, str]]:
    """('file:line', dotted name) of every graftcache.x.y a docstring or comment under PROSE_DIRS names."""
    out = []
    for folder in PROSE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for line, text in prose_of(path.read_text(encoding="utf-8")):
                out += [(f"{path.relative_to(ROOT)}:{line}", d.rstrip(".")) for d in DOTTED.findall(text)]
    return out


def unresolved(cited: list[tuple[str, str]]) -> list[str]:
    """'file:line: dotted: no attribute' for every cited dotted name that does not import or getattr."""
    out = []
    for where, dotted in cited:
        try:
            _resolve(dotted)
        except (AttributeError, AssertionError) as e:
            out.append(f"{where}: {dotted}: no {e}")
    return out


def test_every_dotted_name_in_a_docstring_or_comment_resolves() -> None:
    cited = dotted_in_prose()
    assert len({d for _, d in cited}) >= 100  # the pattern finds the package's citations
    assert unresolved(cited) == []


def test_an_unresolved_dotted_name_is_reported_with_its_line() -> None:
    source = ('"""Reads graftcache.results.SCHEMA.\n\nand graftcache.results.no_such."""\n'
              'x = 1  # graftcache.nowhere.y\n')
    cited = [("f.py:" + str(line), d) for line, text in prose_of(source) for d in DOTTED.findall(text)]
    assert unresolved(cited) == ["f.py:3: graftcache.results.no_such: no no_such",
                                 "f.py:4: graftcache.nowhere.y: no nowhere"]

# ------------------------------------------------------------------------------------------------ the backbone lists
def _specs() -> dict:
    from graftcache.backbone_registry import BACKBONES
    from graftcache.backbones import get_backbone

    return {name: get_backbone(name).spec for name in BACKBONES}


def _lerobot_extras() -> set[str]:
    """The extras of pyproject.toml's lerobot requirement (`lerobot[smolvla,pi,...]`)."""
    import tomllib

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["dependencies"]
    (lerobot,) = [d for d in deps if re.match(r"lerobot\[", d)]
    return set(lerobot.split("[", 1)[1].split("]", 1)[0].split(","))


def test_the_readme_names_every_backbone_and_the_set_up_the_extra_that_installs_it() -> None:
    """README.md's list of backbones and docs/setup.md's of lerobot extras are the registry's: each spec's label and
    extra."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    setup = (ROOT / "docs/setup.md").read_text(encoding="utf-8")
    specs = _specs()
    assert [n for n, s in specs.items() if s.label not in readme] == [], "README.md lacks their BackboneSpec.label"
    assert [n for n, s in specs.items() if s.lerobot_extra and f"`{s.lerobot_extra}`" not in setup] == [], \
        "docs/setup.md does not name their BackboneSpec.lerobot_extra"


def test_pyproject_installs_every_backbone_s_lerobot_extra() -> None:
    extras = _lerobot_extras()
    assert "smolvla" in extras and "dataset" in extras
    assert [f"{n}: lerobot[{s.lerobot_extra}]" for n, s in _specs().items()
            if s.lerobot_extra and s.lerobot_extra not in extras] == []


def test_the_module_map_describes_only_registered_backbones() -> None:
    """The module map's backbones entry names backbone folders (`smolvla/`, `groot/construct.py`): each is one."""
    from graftcache.backbone_registry import BACKBONES

    text = (ROOT / "docs/ARCHITECTURE.md").read_text(encoding="utf-8")
    entry = text.split("    graftcache/backbones/", 1)[1].split("\n    graftcache/", 1)[0]
    named = set(re.findall(r"(?<![\w/.<])(\w+)/(?=[\s,)]|\w+\.py)", entry)) - {"graftcache"}
    assert len(named) >= 5
    assert sorted(named - set(BACKBONES)) == []


def test_the_docs_state_the_current_formats_by_their_constants() -> None:
    """docs/commands.md names the cache and results formats by the constants that decide them, never by a digit that
    goes stale when a format is added (it said results format 4 while the code wrote 5), and no page mentions a
    results format past the current one."""
    from graftcache import results

    readme = " ".join((ROOT / "docs/commands.md").read_text(encoding="utf-8").split())
    assert ("Caches carry a format version (`graftcache.store.manifest.FORMAT_VERSION`), results files their own "
            "(`graftcache.results.FORMAT_VERSION`)") in readme
    assert re.findall(r"(?:format version|their own) \(\d+\)", readme) == []
    every = " ".join(" ".join((ROOT / doc).read_text(encoding="utf-8").split()) for doc in DOCS)
    named = [int(n) for n in re.findall(r"results (?:files? )?(?:of )?format (\d+)", every)]
    assert [n for n in named if n > results.FORMAT_VERSION] == []


# ------------------------------------------------------------------------------- prose that goes stale unseen
#: A date, an issue number or a measured figure (a timing, a rate, a speed ratio) in a docstring or comment goes stale
#: without anything failing: it belongs in benchmarks/results, docs/measured.md or the commit message
STALE = re.compile(r"\b20\d\d-\d\d-\d\d\b|\b[Ii]ssue #?\d+\b"
                   r"|\b\d[\d.,]*\s?(?:ms|s|sec|seconds|minutes|min|hours)\b(?!-)"
                   r"|\b\d[\d.,]*\s?(?:img|images|frames|episodes?|it|samples|steps|[KMG]i?B)/s\b"
                   r"|\b\d[\d.]*x (?:faster|slower)\b")


def toml_comments(text: str) -> list[tuple[int, str]]:
    """(line, comment) of a recipe: what follows each `#` (no recipe value holds one)."""
    return [(i, line.split("#", 1)[1]) for i, line in enumerate(text.splitlines(), 1) if "#" in line]


def test_no_date_issue_number_or_measured_figure_in_code_prose_or_recipe_comments() -> None:
    prose = [(path, prose_of(path.read_text(encoding="utf-8"))) for path in sorted((ROOT / "graftcache").rglob("*.py"))]
    prose += [(path, toml_comments(path.read_text(encoding="utf-8"))) for path in sorted((ROOT / "cli").glob("*.toml"))]
    found = [f"{path.relative_to(ROOT)}:{line}: {m.group(0)!r}" for path, lines in prose for line, text in lines
             if (m := STALE.search(text))]
    assert found == []


def test_a_date_issue_number_or_measured_figure_in_a_comment_or_docstring_is_found() -> None:
    source = ('"""Measured on 2026-11-28."""\nx = "issue 41"  # since issue 41\ny = "2026-11-28"\n'
              '# ~1.2 s a cell\n# 250 frames/s\n# 30x slower\n# 3 seconds\n# a 10-minute budget, 8 steps, 4 MiB\n')
    assert [(line, STALE.search(text).group(0)) for line, text in prose_of(source) if STALE.search(text)] == [
        (1, "2026-11-28"), (2, "issue 41"), (4, "1.2 s"), (5, "250 frames/s"), (6, "30x slower"), (7, "3 seconds")]
    assert toml_comments('steps = 20  # 12 ms a sample\n# a line\nlr = 1e-3\n') == [(1, " 12 ms a sample"),
                                                                                    (2, " a line")]


# ---------------------------------------------------------------------------------------- the commands the docs show
def shown_commands(text: str) -> list[tuple[int, str]]:
    """(line, command) of each `graftcache ...` line inside the fenced code blocks of a doc, its `\\` continuations
    joined and its trailing `# comment` dropped."""
    out, fenced, pending = [], False, None
    for number, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            continue
        if pending is not None:
            pending = (pending[0], pending[1] + " " + line.strip())
        elif line.strip().startswith("graftcache "):
            pending = (number, line.strip())
        if pending is not None and not pending[1].endswith("\\"):
            out.append((pending[0], re.sub(r"\s+#.*$", "", pending[1])))
            pending = None
        elif pending is not None:
            pending = (pending[0], pending[1][:-1].rstrip())
    return out


def test_every_command_the_docs_show_parses_and_names_real_controls() -> None:
    """Each `graftcache ...` line of a doc's code blocks is a command line the CLI takes (its words after `graftcache`
    parsed by graftcache.cli.build_parser, placeholders such as KEY taken as values), and each control it names is
    a registered control: a renamed flag, subcommand or control breaks the doc here, not in a reader's shell."""
    import shlex

    from graftcache.cli import build_parser
    from graftcache.fit.controls import get_control

    parser, shown, broken = build_parser(), 0, []
    for doc in ("README.md", *PAGES):
        for line, command in shown_commands((ROOT / doc).read_text(encoding="utf-8")):
            shown += 1
            words = shlex.split(command)[1:]
            try:
                args = parser.parse_args(words)
                for control in getattr(args, "controls", None) or ():
                    get_control(control)
            except SystemExit:
                broken.append(f"{doc}:{line}: {command}")
            except Exception as e:  # the refusal is the finding
                broken.append(f"{doc}:{line}: {command}: {e}")
    assert shown > 20
    assert broken == []


def test_shown_commands_joins_continuations_and_drops_comments() -> None:
    text = "graftcache ls\n```bash\ngraftcache fit --a 1 \\\n    --b 2   # two flags\ncd x\ngraftcache ls # list\n```\n"
    assert shown_commands(text) == [(3, "graftcache fit --a 1 --b 2"), (6, "graftcache ls")]
