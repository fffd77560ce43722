"""Progress of `mcillum validate` (validation/run/progress.py) and Mitsuba's
log during a run (validation/run/mitsuba_log.py): on a terminal one
updating line; in a log (CI) plain lines, one per stage and at least one per
:data:`progress.INTERVAL` while renders finish, no ANSI escapes, and a
refusal warning said once for all the estimators it concerns."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import textwrap

import mitsuba as mi
import pytest

from mcillum.validation.run import mitsuba_log, progress

#: A progress line in a log: [done/total] what (elapsed, ETA).
LINE = re.compile(r"^\[(\d+)/(\d+)\] (.*) \((.+) elapsed, ETA (.+)\)$")


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


def lines_of(stream) -> list[str]:
    text = stream.getvalue()
    assert "\r" not in text and "\x1b" not in text, repr(text)
    return text.splitlines()


def test_a_log_gets_a_line_per_stage_and_one_at_least_every_interval():
    """A long run of renders 7 s apart: a line when each stage starts, then
    one whenever 30 s have passed since the last, each with done/total and
    an ETA from the pace so far. A progress that goes silent between stages
    fails the largest-gap assertion."""
    clock, out = Clock(), io.StringIO()
    bar = progress.Progress(200, stream=out, tty=False, clock=clock, interval_s=30)
    assert bar.mode == "lines"
    bar.stage("scene cornell_box", "render_ladder", "cornell_box")
    when = [clock.now]
    for k in range(100):
        clock.now += 7
        before = len(out.getvalue())
        bar(f"cornell_box cosine_hemisphere {k} spp")
        if len(out.getvalue()) > before:
            when.append(clock.now)
    bar.stage("scene cornell_box", "build_reference", "cornell_box")
    for _ in range(3):
        clock.now += 7
        bar("reference pass 1 (64 spp)")
    bar.close()
    lines = lines_of(out)
    assert lines[0] == "[0/200] scene cornell_box, render ladder (0 s elapsed, ETA unknown)"
    gaps = [b - a for a, b in zip(when, when[1:])]
    assert len(when) >= 700 // 35 and max(gaps) <= 35, gaps     # never silent 35 s
    assert min(gaps) >= 30, gaps                                  # never chattier
    # The render a line names, without the scene's label (the stage names it);
    # done/total and ETA = elapsed / done × renders left.
    m = LINE.match(lines[1])
    assert m, lines[1]
    done, total = int(m[1]), int(m[2])
    assert (done, total) == (5, 200) and m[3] == ("scene cornell_box, render ladder: "
                                                  "cosine_hemisphere 4 spp")
    assert m[4] == "35 s" and m[5] == progress.duration(35 / 5 * 195) == "22 min 45 s"
    assert "scene cornell_box, build reference (11 min 40 s elapsed, ETA 11 min 40 s)" \
        in lines[-2]
    assert lines[-1] == "[100/200] renders done in 12 min 01 s"
    assert all(LINE.match(line) for line in lines[:-1]), lines


def test_a_terminal_keeps_one_updating_line_and_quiet_is_silent():
    clock, out = Clock(), io.StringIO()
    bar = progress.Progress(4, stream=out, tty=True, clock=clock, interval_s=30)
    bar.stage("scene a", "load", "a")
    for k in range(4):
        clock.now += 60
        bar(f"a path {k} spp")
    assert out.getvalue().count("\r") == 4 and "\n" not in out.getvalue()
    assert out.getvalue().endswith("\r[4/4] a path 3 spp" + " " * 49 + "ETA     0 s")
    bar.close()
    assert out.getvalue().endswith("\n")
    quiet = io.StringIO()
    bar = progress.Progress(4, False, stream=quiet, tty=False, clock=clock, interval_s=30)
    bar.stage("scene a", "load", "a")
    clock.now += 100
    bar("a path 1 spp")
    bar.close()
    assert quiet.getvalue() == "" and bar.done == 1


def test_the_interval_comes_from_the_environment(monkeypatch):
    monkeypatch.delenv(progress.INTERVAL_ENV, raising=False)
    assert progress.interval() == progress.INTERVAL == 30
    monkeypatch.setenv(progress.INTERVAL_ENV, "0.5")
    assert progress.interval() == 0.5
    for bad in ("0", "-1", "soon", "nan"):
        monkeypatch.setenv(progress.INTERVAL_ENV, bad)
        with pytest.raises(ValueError, match=f"{progress.INTERVAL_ENV} must be a positive"):
            progress.interval()


def test_mitsuba_warnings_are_plain_and_one_per_text_in_a_log():
    """Mitsuba's StreamAppender colours every warning, terminal or not; in
    a log the warnings come plain, the same refusal for three estimators in
    one line naming them, in order with the other messages; Mitsuba's own
    appender comes back afterwards."""
    logger = mi.logger()
    own = [logger.appender(i) for i in range(logger.appender_count())]
    out = io.StringIO()
    with mitsuba_log.plain(out) as log:
        assert [logger.appender(i) for i in range(logger.appender_count())] == [log]
        for name in ("cosine_hemisphere", "uniform_hemisphere", "cosine_hemisphere", "mis"):
            mi.Log(mi.LogLevel.Warn, f"{name} with allow_unreachable=true: the image is "
                   "BIASED, it lacks the contribution of delta emitter 'key_light'")
        mi.Log(mi.LogLevel.Warn, "another warning")
        mi.Log(mi.LogLevel.Warn, "mis with allow_unreachable=true: it lacks the sun")
        log.flush()
        assert out.getvalue().count("\n") == 3
        mi.Log(mi.LogLevel.Warn, "mis with allow_unreachable=true: it lacks the sun")
    assert [logger.appender(i) for i in range(logger.appender_count())] == own
    lines = lines_of(out)
    assert len(lines) == 4, lines
    assert lines[0].endswith(": 3 integrators (cosine_hemisphere, uniform_hemisphere, mis) "
                             "with allow_unreachable=true: the image is BIASED, it lacks "
                             "the contribution of delta emitter 'key_light'"), lines[0]
    assert "WARN" in lines[0] and "test_progress.py" in lines[0]     # Mitsuba's format
    assert lines[1].endswith(": another warning")
    assert lines[2].endswith(": mis with allow_unreachable=true: it lacks the sun")
    assert lines[3].endswith(lines[2].split("] ", 1)[1])    # said again after a flush
    coloured = io.StringIO()
    with mitsuba_log.plain(coloured, colour=True):
        mi.Log(mi.LogLevel.Warn, "on a terminal")
    assert coloured.getvalue().startswith("\r\x1b[K\x1b[31m")


def test_a_validation_log_shows_progress_without_escapes(tmp_path):
    """A real run with stderr piped, as in CI: a line per stage, progress
    lines with done/total and an ETA (the interval shortened so that a short
    run writes them), one line for the refusal warning both estimators got,
    and no escape byte; --quiet keeps only that warning."""
    args = [sys.executable, "-m", "mcillum.validation.cli", "validate", "--groups", "failures",
            "--scenes", "point_light", "--estimators", "cosine_hemisphere",
            "uniform_hemisphere", "--out", str(tmp_path / "out"), "--cache",
            str(tmp_path / "cache")]
    env = {**os.environ, progress.INTERVAL_ENV: "1e-9"}
    run = subprocess.run(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    out = run.stdout
    assert run.returncode == 0, out.decode()
    assert b"\x1b" not in out and b"\r" not in out, out
    lines = out.decode().splitlines()
    said = [m for m in map(LINE.match, lines) if m]
    case = "failures.unreachable.point_light"
    stages = [m[3].split(", ", 1)[1] for m in said if m[3].startswith(case + ", ")
              and ": " not in m[3]]
    assert stages[:4] == ["load", "probe refusals", "render seeds", "build reference"], stages
    renders = [m for m in said if re.search(r"render seeds: \w+ 16 spp$", m[3])]
    assert len(renders) == 48, lines                    # 16 seeds × 3: every one at 1e-9 s
    assert [int(m[1]) for m in renders] == list(range(1, 49))
    assert {int(m[2]) for m in said} == {48}
    assert any(m[5].endswith(" s") for m in renders)    # an ETA in seconds
    assert "[48/48] renders done in " in out.decode()
    warned = [line for line in lines if "allow_unreachable=true" in line]
    assert len(warned) == 1 and "2 integrators (cosine_hemisphere, uniform_hemisphere) with" \
        in warned[0], warned
    rerun = subprocess.run([*args, "--quiet"], stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, env=env)
    assert rerun.returncode == 0 and b"\x1b" not in rerun.stdout
    assert not any(map(LINE.match, rerun.stdout.decode().splitlines())), rerun.stdout.decode()
    assert b"PASSED" in rerun.stdout


def test_a_python_plugin_that_logs_while_loading_under_the_run_log_does_not_deadlock():
    """Under the run's log (a Python appender), a scalar variant loads a
    scene whose Python integrator logs from its constructor (Mitsuba warns
    that Python plugins are slow in scalar_*) while a sphere logs its own
    warning. Loaded on Mitsuba's loader threads, this hung for good (CI's
    default run timed out on it); in a subprocess, so a regression fails
    rather than hangs the suite."""
    script = textwrap.dedent("""
        import io, mcillum
        from mcillum.validation.run import mitsuba_log, renders
        from mcillum.validation.plan import scenes
        renders.set_variant("scalar_rgb")
        path = scenes.index()["edge_light_size"].path
        out = io.StringIO()
        with mitsuba_log.plain(out):
            for _ in range(5):
                renders.load_scene(path, res=2, radius=0)
        assert "slow" in out.getvalue() or "performance" in out.getvalue(), out.getvalue()
        assert "non-uniform scaling" in out.getvalue(), out.getvalue()
        print("loaded")
    """)
    try:
        done = subprocess.run([sys.executable, "-c", script], capture_output=True,
                              text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("loading a scene under the run's log deadlocked (see renders.load_resolved)")
    assert done.returncode == 0 and "loaded" in done.stdout, done.stderr[-2000:]
