"""The package's layout keeps its order: every import points down the table of
layers in validation/__init__.py's docstring (the one place the order is
written), and no two modules import each other, directly or round a cycle.

The checker reads each module's imports with ``ast`` (module-level and
inside functions alike; nothing is imported or run), so it sees what the
code says, not what one test run happened to load. Its own tests feed it a
deliberately upward import and a cycle, and check that it names them.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from conftest import ROOT

#: Where each folder's modules live in the import package (pyproject.toml).
FOLDERS = {"mcillum": "mcillum", "integrators": "mcillum.integrators",
           "envmaps": "mcillum.envmaps", "validation": "mcillum.validation"}

#: The longest a module of validation/ may grow before it is split.
MAX_LINES = 400


def package_sources(root: Path = ROOT) -> dict[str, tuple[str, str]]:
    """{dotted module name: (path relative to the checkout, source)} of every
    module of the import package."""
    out = {}
    for folder, package in FOLDERS.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = list(path.relative_to(root / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            name = ".".join([package, *parts])
            out[name] = (str(path.relative_to(root)), path.read_text(encoding="utf-8"))
    return out


def layers(doc: str) -> list[list[str]]:
    """The rows of the table under "Layers, top to bottom:" in ``doc``: each
    row the dotted names (relative to ``mcillum``) it holds."""
    block = doc.split("Layers, top to bottom:", 1)[1]
    rows = [re.split(r"\s{2,}", line.strip(), maxsplit=1)[0].split()
            for line in block.splitlines() if line.startswith("    ") and line.strip()]
    return [["mcillum" if n == "mcillum" else f"mcillum.{n}" for n in row] for row in rows]


def imports(name: str, source: str, known) -> list[tuple[str, int]]:
    """(module imported, line) for every import of one of ``known`` in
    module ``name``: ``from pkg import x`` counts as importing pkg.x where
    that is a module, else pkg itself."""
    is_package = f"{name}.__init__" in known or any(k.startswith(name + ".") for k in known)
    here = name.split(".") if is_package else name.split(".")[:-1]
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name in known]
        elif isinstance(node, ast.ImportFrom):
            base = here[:len(here) - node.level + 1] if node.level else []
            full = ".".join(base + ([node.module] if node.module else []))
            if full not in known:
                continue
            for a in node.names:
                sub = f"{full}.{a.name}"
                out.append((sub if sub in known else full, node.lineno))
    return out


def row_of(name: str, rows: list[list[str]]) -> int | None:
    """The row that holds module ``name``: its own name, or the longest
    package of it named in a row; the two packages that hold other rows
    (mcillum, mcillum.validation) hold only their own ``__init__``."""
    containers = {r for row in rows for r in row
                  if any(o.startswith(r + ".") for other in rows for o in other)}
    best, found = -1, None
    for i, row in enumerate(rows):
        for prefix in row:
            exact = name == prefix
            inside = name.startswith(prefix + ".") and prefix not in containers
            if (exact or inside) and len(prefix) > best:
                best, found = len(prefix), i
    return found


def violations(sources: dict[str, tuple[str, str]], rows: list[list[str]]) -> list[str]:
    """Every import that points up the table, every module the table does not
    place, and every cycle, each named."""
    known = set(sources)
    out, graph = [], {}
    for name, (path, source) in sources.items():
        mine = row_of(name, rows)
        if mine is None:
            out.append(f"{path} ({name}) has no row in the table of layers")
            continue
        graph[name] = set()
        for target, line in imports(name, source, known):
            if target == name:
                continue
            graph[name].add(target)
            theirs = row_of(target, rows)
            if theirs is not None and theirs < mine:
                out.append(f"{path}:{line}: {name} imports {target}, which sits above it "
                           f"({' '.join(rows[theirs])} is above {' '.join(rows[mine])})")
    out += [f"import cycle: {' → '.join([*c, c[0]])}" for c in cycles(graph)]
    return out


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def table() -> list[list[str]]:
    return layers((ROOT / "validation" / "__init__.py").read_text(encoding="utf-8"))


# ----------------------------------- The package ------------------------------------

def test_every_import_points_down_and_nothing_cycles():
    found = violations(package_sources(), table())
    assert not found, "\n".join(found)


def test_the_table_names_only_what_exists():
    """A row that names no module is a stale row."""
    names = set(package_sources())
    for row in table():
        for prefix in row:
            assert any(n == prefix or n.startswith(prefix + ".") for n in names), \
                f"the table of layers names {prefix}, which is no module of the package"


def test_validation_is_in_folders_that_read_as_the_pipeline():
    folders = sorted(p.name for p in (ROOT / "validation").iterdir()
                     if p.is_dir() and (p / "__init__.py").exists())
    assert folders == sorted(["plan", "run", "stats", "stages", "checks", "results", "report"])


def test_no_module_of_validation_is_over_the_limit():
    long = [f"{path}: {len(src.splitlines())} lines"
            for name, (path, src) in package_sources().items()
            if name.startswith("mcillum.validation") and len(src.splitlines()) > MAX_LINES]
    assert not long, f"split these modules (at most {MAX_LINES} lines): {long}"


# ------------------------------- The checker itself ---------------------------------

def _with(sources, name, extra):
    path, src = sources[name]
    return {**sources, name: (path, src + "\n" + extra + "\n")}


def test_an_upward_import_is_named():
    sources = package_sources()
    broken = _with(sources, "mcillum.validation.stats.metrics",
                   "from ..stages import scene  # deliberately upward")
    found = violations(broken, table())
    assert any("mcillum.validation.stats.metrics imports mcillum.validation.stages.scene"
               in f for f in found), found


def test_an_upward_import_inside_a_function_is_named():
    sources = package_sources()
    broken = _with(sources, "mcillum.integrators.core.registry",
                   "def f():\n    from mcillum.validation import pipeline")
    found = violations(broken, table())
    assert any("mcillum.integrators.core.registry imports mcillum.validation.pipeline" in f
               for f in found), found


def test_a_cycle_within_one_layer_is_named():
    sources = package_sources()
    broken = _with(sources, "mcillum.validation.run.jobs",
                   "from . import references  # references imports jobs")
    found = violations(broken, table())
    assert any(f.startswith("import cycle:") and "mcillum.validation.run.jobs" in f
               and "mcillum.validation.run.references" in f for f in found), found


def test_a_module_without_a_row_is_named(tmp_path):
    sources = {**package_sources(),
               "mcillum.newthing": ("mcillum/newthing.py", "import os\n")}
    found = violations(sources, table())
    assert any("mcillum/newthing.py (mcillum.newthing) has no row" in f for f in found), found


@pytest.mark.parametrize("line, target", [
    ("from mcillum import files", "mcillum.files"),
    ("from . import evidence", "mcillum.validation.checks.evidence"),
    ("from ..results import Check", "mcillum.validation.results"),
    ("from .. import results", "mcillum.validation.results"),
    ("import mcillum", "mcillum"),
])
def test_imports_resolve_to_modules(line, target):
    known = set(package_sources())
    assert imports("mcillum.validation.checks.scene", line, known) == [(target, 1)]
