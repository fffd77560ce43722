"""The package's layout keeps its order: every import of every module of the
package (mcillum/, integrators/, envmaps/, validation/) points down the
table of layers in validation/__init__.py's docstring, whose row
``integrators`` is spelled out, family by family, in integrators/__init__.py's
docstring (the one place each order is written); no two modules import each
other, directly or round a cycle; and no module passes :data:`MAX_LINES`
but those :data:`LONG` lists, none longer than it says.

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

#: Packages whose row of the outer table their own docstring spells out, as
#: a table of the same form, in its place.
NESTED = {"mcillum.integrators": "integrators/__init__.py"}

#: The longest a module may grow before it is split.
MAX_LINES = 400

#: The modules over MAX_LINES today, at their length today: each may shrink,
#: none may grow, and no other module may pass the limit.
LONG: dict[str, int] = {}


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


def docstring(path: Path) -> str:
    """The docstring of the module at ``path`` ("" if it has none)."""
    return ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")), clean=False) or ""


def table(root: Path = ROOT) -> list[list[str]]:
    """The rows of the whole package, top to bottom: validation/__init__.py's
    table with each row of :data:`NESTED` replaced by its package's own."""
    rows = []
    for row in layers(docstring(root / "validation" / "__init__.py")):
        nested = NESTED.get(row[0]) if len(row) == 1 else None
        rows += layers(docstring(root / nested)) if nested else [row]
    return rows


def too_long(sources: dict[str, tuple[str, str]], allowed: dict[str, int] = LONG,
             limit: int = MAX_LINES) -> list[str]:
    """Every module over ``limit`` lines that ``allowed`` does not list, or
    longer than ``allowed`` says it is, each named with its length."""
    out = []
    for path, source in sources.values():
        n = len(source.splitlines())
        if n > max(limit, allowed.get(path, 0)):
            known = f" (allowed {allowed[path]})" if path in allowed else ""
            out.append(f"{path}: {n} lines{known}")
    return out


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


def test_integrators_are_in_folders_by_family():
    folders = sorted(p.name for p in (ROOT / "integrators").iterdir()
                     if p.is_dir() and (p / "__init__.py").exists())
    assert folders == sorted(["core", "mc", "quadrature", "guiding", "bsdfs"])
    loose = sorted(p.name for p in (ROOT / "integrators").glob("*.py"))
    assert loose == ["__init__.py", "_llvm.py"], loose


def test_the_table_holds_the_families_of_integrators():
    rows = [" ".join(row) for row in table()]
    assert rows.index("mcillum.integrators") < rows.index("mcillum.integrators._llvm") \
        < rows.index("mcillum.envmaps"), rows
    for family in ("core", "mc", "quadrature", "guiding", "bsdfs"):
        assert f"mcillum.integrators.{family}" in rows, rows


def test_no_module_is_over_the_limit():
    found = too_long(package_sources())
    assert not found, f"split these modules (at most {MAX_LINES} lines): {found}"


def test_every_long_module_listed_is_still_long():
    """An entry of LONG for a module split below the limit is a stale entry."""
    lengths = {path: len(src.splitlines()) for path, src in package_sources().values()}
    stale = [f"{path}: {lengths.get(path, 'no such module')}" for path in LONG
             if lengths.get(path, 0) <= MAX_LINES]
    assert not stale, f"remove these from LONG: {stale}"


def test_no_module_imports_an_old_integrators_path():
    """The paths before the families (integrators.MOVED) are for users' code
    until 0.2; the package's own modules import the new ones."""
    from mcillum import integrators
    old = {f"mcillum.integrators.{m}" for m in integrators.MOVED}
    found = [f"{path}:{line}: {target}"
             for name, (path, source) in package_sources().items()
             for target, line in imports(name, source, set(package_sources()) | old)
             if target in old]
    assert not found, found


# ------------------------------- The checker itself ---------------------------------

def _with(sources, name, extra):
    path, src = sources[name]
    return {**sources, name: (path, src + "\n" + extra + "\n")}


BROKEN = [
    # (module, what is added to it, what one finding must say)
    ("mcillum.validation.stats.metrics", "from ..stages import scene  # deliberately upward",
     ["mcillum.validation.stats.metrics imports mcillum.validation.stages.scene"]),
    ("mcillum.integrators.core.registry", "def f():\n    from mcillum.validation import pipeline",
     ["mcillum.integrators.core.registry imports mcillum.validation.pipeline"]),
    ("mcillum.validation.run.jobs", "from . import references  # references imports jobs",
     ["import cycle:", "mcillum.validation.run.jobs", "mcillum.validation.run.references"]),
    ("mcillum.integrators.mc.cosine_hemisphere", "from ..guiding import guide  # upward",
     ["mcillum.integrators.mc.cosine_hemisphere imports mcillum.integrators.guiding.guide, "
      "which sits above it"]),
    ("mcillum.integrators.core.estimator", "def f():\n    from ..mc import mis",
     ["mcillum.integrators.core.estimator imports mcillum.integrators.mc.mis"]),
    ("mcillum.integrators.quadrature.gp_settings", "from . import gp_scene  # a cycle",
     ["import cycle:", "quadrature.gp_settings", "quadrature.gp_scene"]),
]


@pytest.mark.parametrize("module, extra, says", BROKEN,
                         ids=["upward", "upward-in-a-function", "cycle-in-a-layer",
                              "upward-between-families", "core-imports-a-family",
                              "cycle-in-a-family"])
def test_a_broken_import_is_named(module, extra, says):
    """An upward import (module level or in a function) or a cycle, in
    validation/ or between and within the integrators' families."""
    found = violations(_with(package_sources(), module, extra), table())
    assert any(all(part in f for part in says) for f in found), found


def test_a_family_without_a_row_is_named():
    sources = {**package_sources(), "mcillum.integrators.newfamily.thing":
               ("integrators/newfamily/thing.py", "from ..core import registry\n")}
    found = violations(sources, table())
    assert any("integrators/newfamily/thing.py (mcillum.integrators.newfamily.thing) has "
               "no row" in f for f in found), found


def _tree(root: Path, files: dict[str, str]) -> None:
    for path, text in files.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_text(text, encoding="utf-8")


#: A package of two families in the form of the real one: an outer table in
#: validation/__init__.py whose row ``integrators`` integrators/__init__.py
#: spells out.
SYNTHETIC = {
    "validation/__init__.py": '"""Layers, top to bottom:\n\n'
                              '    validation   v\n    integrators  i\n"""\n',
    "integrators/__init__.py": '"""Layers, top to bottom:\n\n    integrators       the package\n'
                               '    integrators.fam   a family\n'
                               '    integrators.core  the loops\n"""\n'
                               'from .fam import plugin\n',
    "integrators/core/__init__.py": "",
    "integrators/core/loop.py": "X = 1\n",
    "integrators/fam/__init__.py": "",
    "integrators/fam/plugin.py": "from ..core import loop\n",
}


def test_a_synthetic_tree_in_order_passes(tmp_path):
    _tree(tmp_path, SYNTHETIC)
    rows = table(tmp_path)
    assert [r[0] for r in rows] == ["mcillum.validation", "mcillum.integrators",
                                    "mcillum.integrators.fam", "mcillum.integrators.core"]
    assert violations(package_sources(tmp_path), rows) == []


@pytest.mark.parametrize("module, line, expected", [
    ("integrators/core/loop.py", "from ..fam import plugin",
     "mcillum.integrators.core.loop imports mcillum.integrators.fam.plugin, which sits above"),
    ("integrators/fam/plugin.py", "import mcillum.integrators",
     "import cycle: mcillum.integrators → mcillum.integrators.fam.plugin"),
    ("integrators/core/loop.py", "from . import other",
     "import cycle: mcillum.integrators.core.loop → mcillum.integrators.core.other"),
])
def test_a_synthetic_tree_out_of_order_is_named(tmp_path, module, line, expected):
    _tree(tmp_path, {**SYNTHETIC, "integrators/core/other.py": "from . import loop\n"})
    path = tmp_path / module
    path.write_text(path.read_text() + line + "\n")
    found = violations(package_sources(tmp_path), table(tmp_path))
    assert any(expected in f for f in found), found


def test_a_new_long_module_or_a_grown_one_is_named():
    sources = package_sources()
    broken = {**sources,
              "mcillum.integrators.mc.long": ("integrators/mc/long.py", "x = 1\n" * 401),
              "mcillum.integrators.core.estimator":
                  ("integrators/core/estimator.py", "x = 1\n" * 451)}
    found = too_long(broken)
    assert "integrators/mc/long.py: 401 lines" in found, found
    # (a module allowed its length, grown past it: the allowance is named)
    grown = too_long(broken, {"integrators/core/estimator.py": 450})
    assert any(f.startswith("integrators/core/estimator.py:") and "allowed" in f
               for f in grown), grown
    assert too_long(sources) == []


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
