"""Bad user input: each command answers a mistake with one message that says
what was wrong and what to do, exits 2 (usage: the command line alone is
wrong, including an unknown integrator, integrator parameter or map
parameter, in every subcommand) or 1 (found while loading or rendering),
prints no Python traceback, and leaves no partial file where a complete one is
expected, also when it is interrupted (SIGINT), terminated (SIGTERM) or killed
(SIGKILL) mid-write; a killed writer's hidden temporary file is removed by the
next run into the same directory."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from mcillum import files
from mcillum.integrators.core import registry
from mcillum.validation import cli

from conftest import ROOT, SCENES

CORNELL = str(SCENES / "cornell_box.xml")
CAP = str(SCENES / "cap_plane.xml")
MCILLUM_INTEGRATORS = "mcillum's integrators are " + ", ".join(registry.names())


@pytest.fixture
def tmp(tmp_path, monkeypatch):
    """tmp_path holding bad inputs: a malformed and a binary scene, an EXR with
    a NaN pixel, a regular file (``afile``, to put outputs "under") and a
    directory named like an output (``adir.exr``)."""
    monkeypatch.setenv("MCILLUM_CACHE", str(tmp_path / "cache"))
    (tmp_path / "bad.xml").write_text('<scene version="3.0.0">\n  <shape type="sphere">\n'
                                      '    <bsdf type="diffuse">\n</scene>\n')
    (tmp_path / "binary.xml").write_bytes(bytes(range(256)))
    rgb = np.full((8, 16, 3), 0.5, np.float32)
    rgb[1, 2, 0] = np.nan
    files.write_exr(tmp_path / "nan.exr", rgb)
    (tmp_path / "afile").write_text("a regular file")
    (tmp_path / "adir.exr").mkdir()
    return tmp_path


def run(args, tmp_path, capsys):
    """``mcillum ARGS`` in-process ({tmp} → tmp_path): exit code and stderr."""
    try:
        code = cli.main([a.replace("{tmp}", str(tmp_path)) for a in args])
    except SystemExit as e:                     # argparse: usage errors
        code = e.code
    return code, capsys.readouterr().err


def partials(directory):
    return sorted(str(p) for p in directory.rglob(".partial-*"))


def assert_clean_failure(code, err, expected_code, phrase, tmp_path):
    assert code == expected_code, err
    assert phrase.replace("{tmp}", str(tmp_path)) in err, err
    assert "Traceback" not in err and 'File "' not in err, err
    assert not partials(tmp_path)


RENDER = [
    # (id, arguments after `mcillum render`, exit code, phrase of the message)
    ("malformed-xml", ["{tmp}/bad.xml", "-i", "path"], 1,
     'cannot load scene {tmp}/bad.xml: Parsing of XML file "{tmp}/bad.xml" failed: Start-end '
     "tags mismatch (line 4, col 3): fix the XML at that line"),
    ("binary-scene", ["{tmp}/binary.xml", "-i", "path"], 1, "not a UTF-8 text (XML) file"),
    ("scene-is-directory", ["{tmp}", "-i", "path"], 2, "it is a directory; give an XML file"),
    ("unknown-integrator", [CORNELL, "-i", "nope"], 2,
     f"unknown integrator 'nope': {MCILLUM_INTEGRATORS}; any Mitsuba integrator also works"),
    ("not-an-integrator", [CORNELL, "-i", "phong"], 2,
     f"'phong' is a BSDF plugin, not an integrator: {MCILLUM_INTEGRATORS}"),
    ("unknown-param", [CORNELL, "-i", "cosine_hemisphere", "-p", "foo=1"], 2,
     "integrator 'cosine_hemisphere' has no parameter foo: mcillum's integrators take "
     "max_depth, rr_depth, hide_emitters and allow_unreachable"),
    ("unknown-param-path", [CORNELL, "-i", "path", "-p", "foo=1"], 2,
     "integrator 'path' has no parameter foo"),
    ("unknown-define", [CORNELL, "-i", "path", "-D", "foo=1"], 1,
     "has no $-parameter foo (given with -D); its parameters: integrator, max_depth, spp, res"),
    ("max_depth=abc", [CORNELL, "-i", "cosine_hemisphere", "-p", "max_depth=abc"], 2,
     "integrator 'cosine_hemisphere' rejected -p max_depth=abc: max_depth must be an "
     "integer"),
    ("max_depth=2.5", [CORNELL, "-i", "mis", "-p", "max_depth=2.5"], 2,
     "max_depth must be an integer (<integer name=\"max_depth\" value=\"...\"/>), got float 2.5"),
    ("max_depth=abc-path", [CORNELL, "-i", "path", "-p", "max_depth=abc"], 2,
     "integrator 'path' rejected -p max_depth=abc: The property \"max_depth\" has the wrong "
     "type (expected integer, got string)"),
    ("hide_emitters=3", [CORNELL, "-i", "cosine_hemisphere", "-p", "hide_emitters=3"], 2,
     "The property \"hide_emitters\" has the wrong type (expected boolean, got integer)"),
    ("spp=0", [CORNELL, "-i", "path", "--spp", "0"], 2, "--spp must be >= 1, got 0"),
    ("spp=-3", [CORNELL, "-i", "path", "--spp", "-3"], 2, "--spp must be >= 1, got -3"),
    ("spp=abc", [CORNELL, "-i", "path", "--spp", "abc"], 2,
     "argument --spp: invalid int value: 'abc'"),
    ("seed=-1", [CORNELL, "-i", "path", "--seed", "-1"], 2, "--seed must be in [0, 2^32 - 1]"),
    ("res=abc", [CORNELL, "-i", "path", "-D", "res=abc"], 1,
     'could not parse integer value "abc" (check the values of -D res=abc)'),
    ("res=2.5", [CORNELL, "-i", "path", "-D", "res=2.5"], 1,
     'cornell_box.xml (line 40, col 14): could not parse integer value "2.5"'),
    ("res=0", [CORNELL, "-i", "path", "-D", "res=0"], 1,
     "has a 0x0 film: nothing to render; give it a positive size (got -D res=0)"),
    ("res=-2", [CORNELL, "-i", "path", "-D", "res=-2"], 1,
     "value -2 is out of bounds, must be in the range [0, 4294967295] (check the values of "
     "-D res=-2)"),
    ("envmap-missing", [CAP, "-i", "path", "-D", "envmap=/nonexistent.exr"], 1,
     "environment map not found: /nonexistent.exr; give a map name (see `mcillum envmap "
     "--list`) or the path of an existing .exr file"),
    ("envmap-relative", [CAP, "-i", "path", "-D", "envmap=no_such.exr"], 1,
     f"a relative path is taken from the scene's directory, {SCENES}"),
    ("envmap-nan", [CAP, "-i", "path", "-D", "envmap={tmp}/nan.exr"], 1,
     "environment map {tmp}/nan.exr has 1 NaN values (policy 'clamp'): repair or re-export"),
    ("output-under-a-file", [CORNELL, "-i", "path", "-o", "{tmp}/afile/out.exr"], 2,
     "cannot write output {tmp}/afile/out.exr: {tmp}/afile is a file, not a directory"),
    ("output-in-proc", [CORNELL, "-i", "path", "-o", "/proc/out.exr"], 2,
     "cannot write output /proc/out.exr: no file can be created in /proc"),
    ("output-is-a-directory", [CORNELL, "-i", "path", "-o", "{tmp}/adir.exr"], 2,
     "output {tmp}/adir.exr is a directory: give a file path"),
    ("output-missing-directory", [CORNELL, "-i", "path", "-o", "{tmp}/no/out.exr"], 2,
     "output directory does not exist: {tmp}/no (create it first)"),
]


@pytest.mark.parametrize("args, code, phrase", [c[1:] for c in RENDER],
                         ids=[c[0] for c in RENDER])
def test_render(llvm, tmp, capsys, args, code, phrase):
    args = list(args)
    args += [] if "-o" in args else ["-o", "{tmp}/out.exr"]
    args += [] if "--spp" in args else ["--spp", "1"]
    args += [] if any(a.startswith("res=") for a in args) else ["-D", "res=4"]
    got, err = run(["render", *args], tmp, capsys)
    assert_clean_failure(got, err, code, phrase, tmp)
    assert not (tmp / "out.exr").exists() and not (tmp / "out.png").exists()


ENVMAP = [
    ("missing-file", ["/nonexistent.exr"], 1,
     "environment map not found: /nonexistent.exr; give a map name (see `mcillum envmap "
     "--list`)"),
    ("unknown-name", ["nope"], 1, "environment map not found: nope; give a map name"),
    ("nan-pixel", ["{tmp}/nan.exr"], 1, "has 1 NaN values (policy 'clamp')"),
    ("nan-pixel-strict", ["{tmp}/nan.exr", "--policy", "strict"], 1, "(policy 'strict')"),
    ("param-not-a-number", ["cap", "-p", "alpha_deg=abc"], 2,
     "map 'cap': alpha_deg must be a number, got 'abc'; map 'cap' takes radiance, "
     "alpha_deg, direction"),
    ("param-out-of-range", ["cap", "-p", "alpha_deg=120"], 2,
     "alpha_deg must be in (0, 90], got 120"),
    ("unknown-param", ["cap", "-p", "foo=1"], 2, "map 'cap' has no parameter foo"),
    ("output-under-a-file", ["cap", "-o", "{tmp}/afile/out.exr"], 2,
     "{tmp}/afile is a file, not a directory"),
    ("output-in-proc", ["cap", "-o", "/proc/out.exr"], 2, "no file can be created in /proc"),
]


@pytest.mark.parametrize("args, code, phrase", [c[1:] for c in ENVMAP],
                         ids=[c[0] for c in ENVMAP])
def test_envmap(tmp, capsys, args, code, phrase):
    if "-o" not in args:
        args = [*args, "-o", "{tmp}/out.exr"]
    got, err = run(["envmap", *args], tmp, capsys)
    assert_clean_failure(got, err, code, phrase, tmp)
    assert not (tmp / "out.exr").exists()


VALIDATE = [
    ("unknown-estimator", ["--estimators", "nope"], 2,
     f"unknown integrator 'nope': {MCILLUM_INTEGRATORS}"),
    ("estimator-not-an-integrator", ["--estimators", "diffuse"], 2,
     "'diffuse' is a BSDF plugin, not an integrator"),
    ("out-is-a-file", ["--out", "{tmp}/afile"], 2,
     "--out {tmp}/afile is a file, not a directory: give a directory"),
    ("out-under-a-file", ["--out", "{tmp}/afile/out"], 2,
     "cannot create --out {tmp}/afile/out: Not a directory"),
    ("out-in-proc", ["--out", "/proc/mcillum-out"], 2, "cannot create --out /proc/mcillum-out"),
    ("junit-under-a-file", ["--junit", "{tmp}/afile/junit.xml"], 2,
     "cannot write --junit {tmp}/afile/junit.xml: {tmp}/afile is a file, not a directory"),
    ("cache-under-a-file", ["--cache", "{tmp}/afile/cache"], 2,
     "cannot create the reference cache {tmp}/afile/cache: Not a directory (choose another "
     "with --cache DIR)"),
]


@pytest.mark.parametrize("args, code, phrase", [c[1:] for c in VALIDATE],
                         ids=[c[0] for c in VALIDATE])
def test_validate(llvm, tmp, capsys, args, code, phrase):
    defaults = [] if "--out" in args else ["--out", "{tmp}/out"]
    defaults += [] if "--cache" in args else ["--cache", "{tmp}/cache"]
    got, err = run(["validate", *defaults, *args], tmp, capsys)
    assert_clean_failure(got, err, code, phrase, tmp)
    assert not list(tmp.rglob("results.json"))


REPORT = [
    ("no-results", None, 2, "no results.json in {tmp}/run: run `mcillum validate --out "
                            "{tmp}/run` first"),
    ("truncated", '{"schema": "mcillum.results", "scenes": [', 1,
     "{tmp}/run/results.json is not valid JSON (Expecting value: line 1 column 42"),
    ("not-ours", '{"answer": 42}', 1, "is not an mcillum results file"),
    ("other-version", '{"schema": "mcillum.results", "version": 0}', 1,
     "has results version 0; this mcillum reads version 1: run `mcillum validate --out"),
    ("missing-field", '{"schema": "mcillum.results", "version": 1}', 1,
     "results.json lacks the field 'created': run `mcillum validate --out {tmp}/run` again"),
]


@pytest.mark.parametrize("text, code, phrase", [c[1:] for c in REPORT],
                         ids=[c[0] for c in REPORT])
def test_report(tmp, capsys, text, code, phrase):
    (tmp / "run").mkdir()
    if text is not None:
        (tmp / "run" / "results.json").write_text(text)
    got, err = run(["report", "{tmp}/run"], tmp, capsys)
    assert_clean_failure(got, err, code, phrase, tmp)
    assert not (tmp / "run" / "report").exists()


# ----------------------- interrupted and killed runs --------------------------

#: Runs `mcillum ARGS...` with every atomic write of a file whose name ends in
#: SUFFIX stalled half-way: the temporary file is truncated to half its size,
#: MARKER is created, and the process sleeps until a signal arrives.
STALLED_WRITE = """
import contextlib, os, sys, time
from mcillum import files
from mcillum.integrators.core import registry
from mcillum.validation import cli

suffix, marker = sys.argv[1], sys.argv[2]
real = files.atomic_path

@contextlib.contextmanager
def stalled(path):
    with real(path) as tmp:
        yield tmp
        if str(path).endswith(suffix):
            with open(tmp, "r+b") as f:
                f.truncate(os.path.getsize(tmp) // 2)
            open(marker, "w").close()
            for _ in range(1200):   # busy, as a long write would be
                time.sleep(0.1)

files.atomic_path = stalled
sys.argv = ["mcillum", *sys.argv[3:]]
sys.exit(cli.main())                    # as the console script calls it
"""


def stall_and_signal(tmp_path, suffix, args, sig, deadline=120):
    """Start the stalled command, wait for its stalled write, send ``sig``."""
    marker = tmp_path / "stalled"
    proc = subprocess.Popen([sys.executable, "-c", STALLED_WRITE, suffix, str(marker), *args],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    end = time.time() + deadline
    while not marker.exists() and proc.poll() is None and time.time() < end:
        time.sleep(0.05)
    assert marker.exists(), proc.communicate(timeout=30)
    marker.unlink()
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    return proc.returncode, err


SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGKILL]


@pytest.mark.parametrize("stalled", [".exr", ".png"])
@pytest.mark.parametrize("sig", SIGNALS, ids=[s.name for s in SIGNALS])
def test_render_interrupted_mid_write_leaves_no_truncated_output(tmp_path, sig, stalled):
    out = tmp_path / "out" / "cb.exr"
    out.parent.mkdir()
    args = ["render", CORNELL, "-i", "cosine_hemisphere", "--spp", "1", "-D", "res=4",
            "-o", str(out)]
    code, err = stall_and_signal(tmp_path, stalled, args, sig)
    assert "Traceback" not in err, err
    if sig == signal.SIGINT:
        assert code == 130 and "mcillum render: interrupted; no partial output files" in err
    elif sig == signal.SIGTERM:
        assert code == 143 and "mcillum render: terminated (SIGTERM)" in err
    else:                                    # nothing runs after SIGKILL: a hidden
        assert code == -signal.SIGKILL       # .partial-* stays, never the output
        assert partials(tmp_path)
    if sig != signal.SIGKILL:
        assert not partials(tmp_path), f"{sig.name} must remove the temporary file"
    left = sorted(p.name for p in out.parent.iterdir() if not p.name.startswith(".partial-"))
    if stalled == ".exr":                    # stopped while writing the EXR: no output
        assert left == []
    else:                                    # stopped while writing the PNG: the EXR
        assert left == ["cb.exr"]            # before it is complete, the PNG absent
        image, meta = files.read_exr(out)
        assert image.shape == (4, 4, 3) and meta["spp"] == 1
    if sig == signal.SIGKILL:                # the next run cleans up after the dead one
        done = subprocess.run([sys.executable, "-m", "mcillum.validation.cli", *args],
                              cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert not partials(tmp_path), "the killed writer's temporary file was left"


def test_stale_partials_of_live_processes_are_kept(tmp_path):
    """Only a dead writer's temporary files are removed: a live process (this
    one) may still be writing its own."""
    with files.atomic_path(tmp_path / "x.exr") as tmp:
        assert files.remove_stale_partials(tmp_path) == []
        assert os.path.exists(tmp)


@pytest.mark.parametrize("stage", ["fresh", "over-an-earlier-run", "writing-the-report"])
def test_validate_interrupted_exits_130_without_false_results(tmp_path, stage):
    """SIGINT while a file is being written (a render step, or the report at
    the end): exit 130, one line saying what is left and what to do, no
    temporary files, and no results.json unless this run finished computing it.
    (A SIGKILL'd run and its resumption: test_validate.py's killed-run test.)"""
    out = tmp_path / "out"
    out.mkdir()
    old = '{"schema": "mcillum.results", "created": "2000-01-01T00:00:00"}'
    if stage == "over-an-earlier-run":
        (out / "results.json").write_text(old)
    code, err = stall_and_signal(
        tmp_path, "index.html" if stage == "writing-the-report" else ".npz",
        ["validate", "--out", str(out), "--cache", str(tmp_path / "cache"),
         "--scenes", "furnace_sphere", "--estimators", "cosine_hemisphere", "--quiet"],
        signal.SIGINT)   # (--quiet: no progress lines, only the message is said)
    assert code == 130 and "Traceback" not in err, err
    assert err.startswith("mcillum validate: interrupted: ") and err.count("\n") == 1, err
    assert not partials(tmp_path), "SIGINT must remove the temporary files"
    assert not (out / "report" / "index.html").exists()
    resume = (f"finished renders are kept in {out} and reused: run the same command "
              "again to resume")
    if stage == "fresh":
        assert "interrupted: no results were written; " + resume in err
        assert not (out / "results.json").exists() and not (out / "results.csv").exists()
    elif stage == "over-an-earlier-run":
        assert (f"{out}/results.json is from an earlier run (created 2000-01-01T00:00:00), "
                "not this one; " + resume) in err
        assert (out / "results.json").read_text() == old
    else:
        assert (f"interrupted: while writing the report: {out}/results.json is complete; "
                f"run `mcillum report {out}` to write the report") in err
        assert json.loads((out / "results.json").read_text())["scenes"]
