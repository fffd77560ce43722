"""The documents: README.md and docs/*.md.

* Every relative link and image points at a file that exists, and every
  anchor (``#...``, alone or after a .md path) at a heading of its target,
  by GitHub's slug rules. External links (http, https, mailto) are not
  fetched: a test that needs the network is not a test here.
* README.md stays a front door: at most :data:`README_MAX_LINES` lines, and no
  wall times or test counts in its prose. Those change with every machine and
  every commit; they belong in docs/measurements.md, a dated notebook.

The checkers take the file list, so the tests at the bottom can show on a
broken copy in ``tmp_path`` that each of them fails where it should.
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path
from urllib.parse import unquote

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 250


def doc_files(root: Path = ROOT) -> list[Path]:
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


# ------------------------------- Markdown text ---------------------------------

FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})")
LIST_ITEM = re.compile(r"^\s*([-*+]|\d+[.)])\s")


def prose(text: str) -> str:
    """``text`` with code blanked out: fenced blocks, indented blocks and
    inline code spans become empty or spaces (newlines kept, so line numbers
    hold)."""
    out, fence, code, last_text = [], None, False, ""
    for line in text.split("\n"):
        m = FENCE.match(line)
        if fence:
            out.append("")
            if m and m.group(1)[0] == fence[0] and len(m.group(1)) >= len(fence):
                fence = None
            continue
        if m:
            fence, code = m.group(1), False
            out.append("")
            continue
        blank = not line.strip()
        indented = line.startswith(("    ", "\t")) and not blank
        # an indented block follows a blank line (or continues one), and is
        # not the indented text of a list item
        if indented and (code or (out and not out[-1].strip()
                                  and not LIST_ITEM.match(last_text)
                                  and not last_text.startswith((" ", "\t")))):
            code = True
            out.append("")
            continue
        code = code and blank
        if not blank:
            last_text = line
        out.append(line)
    joined = "\n".join(out)
    # inline code: a run of backticks up to the same run
    return re.sub(r"(`+)(.+?)\1", lambda m: re.sub(r"[^\n]", " ", m.group(0)), joined,
                  flags=re.S)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading's text: lowercase; keep letters (any
    script, with their combining marks), decimal digits, spaces, hyphens and
    underscores (superscripts such as ² go); spaces become hyphens."""
    text = heading.strip().lower()
    keep = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LM"
                   or unicodedata.category(c) == "Nd")
    return keep.replace(" ", "-")


def heading_text(raw: str) -> str:
    """What a heading shows: links by their text, no code marks, emphasis or tags."""
    raw = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", raw)
    raw = re.sub(r"<[^>]+>", "", raw)
    return raw.replace("`", "").replace("*", "")


ATX = re.compile(r"^ {0,3}#{1,6}(?:\s+(.*?))?\s*$")


#: An HTML anchor in the prose: ``<a id="2026-12-06-report-viewer"></a>``.
HTML_ANCHOR = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"")


def anchors(path: Path) -> set[str]:
    """The anchors GitHub gives the headings of ``path`` (duplicates -1, -2, …),
    and the ids of its HTML anchors (``<a id="…">``)."""
    raw_lines = path.read_text(encoding="utf-8").split("\n")
    # which lines are headings is read with code blanked (a "# comment" in a
    # shell block is none); their titles from the raw line, code spans included
    lines = prose("\n".join(raw_lines)).split("\n")
    seen: dict[str, int] = {}
    out = set()
    for i, line in enumerate(lines):
        out.update(HTML_ANCHOR.findall(line))
        title = None
        if ATX.match(line):
            title = re.sub(r"\s+#+$", "", ATX.match(raw_lines[i]).group(1) or "")
        elif (i > 0 and re.match(r"^ {0,3}(=+|-+)\s*$", line) and lines[i - 1].strip()
              and not lines[i - 1].lstrip().startswith(("|", "#", "-", "*", ">"))):
            title = raw_lines[i - 1].strip()            # a setext heading
        if title is None:
            continue
        base = slug(heading_text(title))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


LINK = re.compile(r"(!?)\[((?:[^\[\]]|\[[^\[\]]*\])*)\]\(\s*<?([^\s)>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
DEFINITION = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s.*)?$")
EXTERNAL = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")


def links(path: Path) -> list[tuple[int, str]]:
    """(line, target) of every link, image and link definition outside code."""
    text = prose(path.read_text(encoding="utf-8"))
    found = [(text.count("\n", 0, m.start()) + 1, m.group(3)) for m in LINK.finditer(text)]
    # a definition "[id]: target" starts a block (it cannot interrupt a paragraph)
    lines = text.split("\n")
    for i, line in enumerate(lines):
        m = DEFINITION.match(line)
        if m and (i == 0 or not lines[i - 1].strip() or DEFINITION.match(lines[i - 1])):
            found.append((i + 1, m.group(1)))
    return sorted(found)


def broken_links(files: list[Path], root: Path = ROOT) -> list[str]:
    """One line per broken link: ``file:line: (target): what is wrong and what
    to do``. A path is relative to its file (``/...``: to ``root``)."""
    problems = []
    cache: dict[Path, set[str]] = {}
    for path in files:
        for line, target in links(path):
            where = f"{path.name}:{line}: ({target})"
            if not target:
                problems.append(f"{where}: empty link target")
                continue
            if EXTERNAL.match(target):
                continue                                  # http(s), mailto: not fetched
            file_part, _, anchor = target.partition("#")
            if file_part:
                base = path.parent if not file_part.startswith("/") else root
                dest = (base / unquote(file_part).lstrip("/")).resolve()
                if not dest.exists():
                    problems.append(f"{where}: no such file {dest}; fix the path "
                                    f"(relative to {path.name}) or create the file")
                    continue
            else:
                dest = path
            if anchor and dest.suffix == ".md":
                if dest not in cache:
                    cache[dest] = anchors(dest)
                if unquote(anchor) not in cache[dest]:
                    near = sorted(a for a in cache[dest]
                                  if a.split("-")[0] == unquote(anchor).split("-")[0])
                    problems.append(f"{where}: no heading of {dest.name} has the anchor "
                                    f"#{anchor}; fix the link or the heading"
                                    + (f" (headings like it: {', '.join(near[:5])})"
                                       if near else ""))
    return problems


# --------------------------- What the README states ----------------------------

#: Things that change with the machine or the commit: they go to
#: docs/measurements.md, with a date. Superscripts (2³² samples, 8² pixels) are
#: not digits to \d, so sizes and counts of samples do not trip these.
STATED = [
    (re.compile(r"(?<![\w.])\d+(?:[.,]\d+)?\s?(?:min|mins|minutes?|h|hours?)\b"),
     "a wall time in minutes or hours"),
    (re.compile(r"(?<![\w.])\d+(?:[.,]\d+)?\s?(?:s|ms|secs?|seconds?)\b"),
     "a wall time in seconds"),
    (re.compile(r"(?<![\w.])\d[\d,\u2009\u202f ]*\s(?:tests|test cases)\b"),
     "a test count"),
    (re.compile(r"(?<![\w.])\d+\s(?:of\s\d[\d,\u2009\u202f ]*\s)?checks\b"),
     "a count of checks"),
    (re.compile(r"(?<![\w.])\d+(?:\.\d+)?\s?(?:[KMG]i?B)\b"), "a measured size"),
]


def stated_figures(readme: Path) -> list[str]:
    """One line per wall time, test count, check count or file size in the
    prose of ``readme`` (code blocks and spans left out)."""
    text = prose(readme.read_text(encoding="utf-8"))
    found = sorted((m.start(), " ".join(m.group(0).split()), what)
                   for pattern, what in STATED for m in pattern.finditer(text))
    return [f"{readme.name}:{text.count(chr(10), 0, pos) + 1}: '{figure}' is {what}; move "
            "it into a dated entry of docs/measurements.md and link there"
            for pos, figure, what in found]


def too_long(readme: Path, limit: int = README_MAX_LINES) -> str | None:
    n = len(readme.read_text(encoding="utf-8").splitlines())
    if n > limit:
        return (f"{readme.name} has {n} lines (at most {limit}): move detail into docs/ "
                "and link to it")
    return None


# ------------------------- The code's citations of figures ------------------------

#: A citation of a measurement in the code: ``docs/measurements.md#<anchor>``,
#: or (the old way) a date after the file's name, which heads several entries.
CITED = re.compile(r"measurements\.md(#[\w.-]+)?(?:,?\s+(?:#:?\s*)?(20\d\d-\d\d-\d\d))?")

#: Code allowed to cite a measurement by date: none now (issue 67 converted
#: the last); the test of this set's use stays for a file that needs it.
DATED_FOR_NOW: set[str] = set()


def code_files(root: Path = ROOT) -> list[Path]:
    """The package's and the tests' sources (.py, .toml)."""
    return sorted(p for folder in ("mcillum", "integrators", "envmaps", "validation", "tests")
                  for p in (root / folder).rglob("*") if p.suffix in (".py", ".toml"))


def bad_citations(files: list[Path], root: Path = ROOT, dated_ok=DATED_FOR_NOW) -> list[str]:
    """One line per citation of docs/measurements.md by an anchor it does not
    have, or by a date alone (outside ``dated_ok``)."""
    known = anchors(root / "docs" / "measurements.md")
    out = []
    for path in files:
        rel = path.relative_to(root).as_posix()
        text = path.read_text(encoding="utf-8")
        for m in CITED.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            if m.group(1) and m.group(1)[1:] not in known:
                out.append(f"{rel}:{line}: measurements.md{m.group(1)} names no entry")
            elif m.group(2) and not m.group(1) and rel not in dated_ok:
                out.append(f"{rel}:{line}: cites measurements.md by the date {m.group(2)}, "
                           "which heads several entries: cite the entry's anchor")
    return out


# ------------------------------------ Tests -------------------------------------

def test_every_relative_link_and_anchor_resolves():
    problems = broken_links(doc_files())
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_readme_is_a_front_door():
    problem = too_long(ROOT / "README.md")
    assert problem is None, problem


def test_readme_states_no_wall_times_or_test_counts():
    problems = stated_figures(ROOT / "README.md")
    assert not problems, "\n".join(problems)


# --------------------------- The checkers, checked ------------------------------

def test_the_code_cites_measurements_by_their_anchors():
    problems = bad_citations(code_files())
    assert not problems, "\n".join(problems)


def test_the_citation_check_finds_dates_and_unknown_anchors(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "measurements.md").write_text(
        '# M\n\n<a id="2026-01-01-one"></a>\n## 2026-01-01 — One\n', encoding="utf-8")
    code = tmp_path / "a.py"
    m = "docs/measurements" + ".md"          # (not a citation of this file's own)
    code.write_text(f"# fine ({m}#2026-01-01-one)\n# fine ({m}#m)\n"
                    f"# a date ({m}, 2026-01-01)\n"
                    f"# a date on the next line ({m},\n# 2026-01-01)\n"
                    f"# gone ({m}#2026-01-02-two)\n", encoding="utf-8")
    problems = bad_citations([code], tmp_path, dated_ok=set())
    assert [p.split(":")[1] for p in problems] == ["3", "4", "6"], problems
    assert bad_citations([code], tmp_path, dated_ok={"a.py"})[0].startswith("a.py:6:")


def test_slugs_follow_githubs_rules():
    assert slug("Validation: mcillum validate") == "validation-mcillum-validate"
    assert slug("2026-11-24 — Quick profile") == "2026-11-24--quick-profile"
    assert slug("Équal time, (again) & more") == "équal-time-again--more"
    assert slug("max_depth and rr_depth") == "max_depth-and-rr_depth"
    assert slug("Renders beyond 2³² samples") == "renders-beyond-2-samples"
    assert heading_text("The `path` [reference](x.md)") == "The path reference"


def test_the_link_checker_finds_what_is_broken(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text(
        "# A\n\n## Twice\n\n## Twice\n\n## Équipe\n\n<a id=\"2026-01-01-entry\"></a>\n"
        "`<a id=\"in-code\"></a>`\n", encoding="utf-8")
    (tmp_path / "README.md").write_text(
        "# Readme\n\n"
        "[fine](docs/a.md) [fine](docs/a.md#twice-1) [fine](docs/a.md#équipe)\n"
        "[fine](#readme) [external](https://example.invalid/nowhere) [fine](/docs/a.md)\n"
        "![fine image](docs/a.md)\n"
        "[missing file](docs/b.md)\n"
        "[missing anchor](docs/a.md#twice-2) [fine](docs/a.md#2026-01-01-entry)\n"
        "[missing local\nanchor](#nowhere)\n"
        "![missing image](docs/shot.png)\n"
        "```\n[in code](docs/none.md)\n```\n"
        "`[in a span](docs/none.md)` [anchor in code](docs/a.md#in-code)\n"
        "\n[ref]: docs/gone.md\n"
        "A sentence, not a definition:\n[2/3, 3/2]: pass\n", encoding="utf-8")
    problems = broken_links([tmp_path / "README.md", tmp_path / "docs" / "a.md"], tmp_path)
    assert len(problems) == 6, problems
    for line, target in [(6, "docs/b.md"), (7, "docs/a.md#twice-2"), (8, "#nowhere"),
                         (10, "docs/shot.png"), (14, "docs/a.md#in-code"),
                         (16, "docs/gone.md")]:
        assert any(p.startswith(f"README.md:{line}: ({target})") for p in problems), problems


def test_the_readme_checks_find_times_and_counts(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(
        "# Readme\n\n"
        "It renders 2³² samples of 8² pixels, K = 4 seeds at 16 spp, 0.95 survival;\n"
        "exit 130; α = 0.01; `the 53 s of a span`.\n\n"
        "    make test   # an indented block may say 53 s\n\n"
        "```sh\nmake validate   # 3 min 50 s\n```\n"
        "The quick profile took 3 min 59 s and re-ran in 15 s.\n"
        "The suite has 1120 tests; 194 of 216 checks pass; the report is 6.3 MB.\n",
        encoding="utf-8")
    problems = stated_figures(readme)
    found = [(p.split(":")[1], p.split("'")[1]) for p in problems]
    assert found == [("11", "3 min"), ("11", "59 s"), ("11", "15 s"), ("12", "1120 tests"),
                     ("12", "194 of 216 checks"), ("12", "6.3 MB")], problems
    readme.write_text("line\n" * (README_MAX_LINES + 1), encoding="utf-8")
    assert "at most" in too_long(readme)
    readme.write_text("line\n" * README_MAX_LINES, encoding="utf-8")
    assert too_long(readme) is None


# ------------------------------ The README's picture ------------------------------

def _screenshot_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("screenshot", ROOT / "docs" / "screenshot.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_readmes_picture_of_the_report_shows_the_report_as_it_is_drawn():
    """docs/report-quick.png was taken (docs/screenshot.py) from the report's
    code as it stands: a changed report fails here until `make screenshot`."""
    from PIL import Image

    shot = _screenshot_module()
    picture = ROOT / "docs" / "report-quick.png"
    assert "(docs/report-quick.png)" in (ROOT / "README.md").read_text(encoding="utf-8")
    taken = Image.open(picture).text.get(shot.KEY)
    assert taken == shot.report_code_hash(), (
        "docs/report-quick.png was not taken from the report's code as it stands "
        "(validation/report/ changed): run `make screenshot` and commit the picture")


def test_the_pictures_hash_follows_the_report_code(tmp_path, monkeypatch):
    """The hash changes when a report module changes (a stale picture is seen)."""
    shot = _screenshot_module()
    copy = tmp_path / "report"
    copy.mkdir()
    for f in Path(shot.REPORT_CODE).glob("*.py"):
        (copy / f.name).write_bytes(f.read_bytes())
    monkeypatch.setattr(shot, "REPORT_CODE", str(copy))
    before = shot.report_code_hash()
    with open(copy / "page.py", "a", encoding="utf-8") as f:
        f.write("\n# a change\n")
    assert shot.report_code_hash() != before
