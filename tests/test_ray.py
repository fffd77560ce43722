"""`mcillum validate --executor ray` on a local 2-worker Ray instance gives the
images of the in-process run, bit for bit, even when a worker is killed in
the middle of a render; and a render that fails fails the run as it would
locally.

Ray runs in a subprocess: it binds this machine's own interface address
(never loopback: ray.init resolves 127.0.0.1 to it), which the loopback
guard of conftest.py refuses in the test process; nothing leaves the
machine. Skipped where Ray is not installed (`pip install -e '.[ray]'`;
.ci/run installs it).
"""

from __future__ import annotations

import glob
import importlib.util
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from mcillum import files

pytestmark = [pytest.mark.ray, pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="Ray is not installed: pip install -e '.[ray]' (the ray extra; .ci/run installs it)")]

#: One quick scene with its failure case (lone_sphere: the ladder, the
#: quadrature stage with its timed equal-ray pair, references, and the
#: sunrise case with its sunless twin), four estimators to keep it short.
ARGS = ["validate", "--profile", "quick", "--scenes", "lone_sphere", "--no-speed",
        "--estimators", "cosine_hemisphere", "fibonacci_hemisphere", "bayesian_hemisphere",
        "path"]
WORKER = "ray::RenderWorker"


#: The quick profile without its reference time cap: a reference stopped by
#: the clock depends on the machine's speed (docs/machines.md), and CI is slow.
UNCAPPED = """
import dataclasses, sys
from mcillum.validation import cli
from mcillum.validation.plan import profiles
profiles.PROFILES["quick"] = dataclasses.replace(profiles.QUICK, reference_max_seconds=3600.0)
sys.exit(cli.main(sys.argv[1:]))
"""


def _mcillum(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", UNCAPPED, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _process_table() -> dict[int, tuple[int, str]]:
    """pid → (parent pid, command line as the process shows it)."""
    table = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                parent = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except (OSError, IndexError, ValueError):
            continue
        table[int(entry)] = (parent, cmd)
    return table


def _workers(root: int) -> dict[int, str]:
    """The render workers among the descendants of process ``root``."""
    table = _process_table()
    children: dict[int, list[int]] = {}
    for pid, (parent, _) in table.items():
        children.setdefault(parent, []).append(pid)
    out, todo = {}, [root]
    while todo:
        for pid in children.get(todo.pop(), []):
            todo.append(pid)
            if table[pid][1].startswith(WORKER):
                out[pid] = table[pid][1]
    return out


def _exr_pixels(path: str) -> dict[str, np.ndarray]:
    import OpenEXR
    with OpenEXR.File(path) as f:
        return {name: np.asarray(ch.pixels) for part in f.parts
                for name, ch in part.channels.items()}


#: results.json fields that hold or follow from wall times, or say where the
#: run happened: the only ones allowed to differ.
TIMING = {"created", "wall_seconds", "executor", "seconds", "median_seconds",
          "seconds_median", "compile_seconds", "samples_per_second", "efficiency",
          "baseline_seconds", "report"}


def _differences(a, b, where="", rel=0.0) -> list[str]:
    """Where results ``a`` and ``b`` differ, TIMING's fields left out. An
    estimator's ``settings`` may differ by 1e-8 relative: the driver scores
    them itself in numpy (ill-conditioned linear solves), and a driver that
    rendered and one that did not differ there by ~1e-11 (LAPACK/BLAS
    reductions), though the choice and every image agree bit for bit."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() - TIMING != b.keys() - TIMING:
            return [f"{where}: keys {sorted(a.keys() ^ b.keys())}"]
        return [d for k in a.keys() - TIMING
                for d in _differences(a[k], b[k], f"{where}/{k}", 1e-8 if k == "settings" else rel)]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} items, {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{where}[{i}]", rel)]
    if isinstance(a, float) and isinstance(b, float) and rel > 0 and math.isclose(a, b, rel_tol=rel):
        return []
    same = a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))
    return [] if same else [f"{where}: {a!r} != {b!r}"]


@pytest.mark.slow          # (two runs and a Ray cluster's start: the longest test)
def test_ray_run_gives_the_local_images_even_when_a_worker_dies(tmp_path):
    local = _mcillum(*ARGS, "--out", str(tmp_path / "local"), "--cache", str(tmp_path / "c1"))
    out, err = local.communicate(timeout=900)
    assert local.returncode == 0, err

    # the same run on 2 workers (its own cache: its references are rendered
    # too); one worker is killed while it renders
    remote = _mcillum(*ARGS, "--out", str(tmp_path / "ray"), "--cache", str(tmp_path / "c2"),
                      "--executor", "ray", "--ray-workers", "2")
    seen, killed = set(), None
    deadline = time.monotonic() + 900
    while remote.poll() is None and time.monotonic() < deadline:
        workers = _workers(remote.pid)
        seen |= set(workers)
        busy = [pid for pid, cmd in workers.items() if cmd.startswith(f"{WORKER}.render")]
        if killed is None and busy and len(seen) >= 2:
            killed = busy[0]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    out, err = remote.communicate(timeout=60)
    assert remote.returncode == 0, err
    assert killed is not None, "no worker was seen rendering"
    assert len(seen) >= 3, f"the killed worker was not replaced: {seen}"   # a restart

    # every EXR, every layer, bit for bit
    a, b = (sorted(os.path.relpath(p, tmp_path / d)
                   for p in glob.glob(f"{tmp_path / d}/**/*.exr", recursive=True))
            for d in ("local", "ray"))
    assert a == b and len(a) >= 15          # (4 estimators: renders, means, evidence)
    for name in a:
        x, y = (_exr_pixels(str(tmp_path / d / name)) for d in ("local", "ray"))
        assert x.keys() == y.keys(), name
        for layer in x:
            assert x[layer].dtype == y[layer].dtype and \
                np.array_equal(x[layer], y[layer], equal_nan=True), f"{name} {layer}"

    # results.json: the same but for timings and where it ran
    first, second = (json.load(open(tmp_path / d / "results.json")) for d in ("local", "ray"))
    assert first["executor"]["kind"] == "local" and second["executor"]["kind"] == "ray"
    assert second["executor"]["workers"] == 2
    assert not any("time" in (s["reference"]["capped"] or "") for s in first["scenes"])
    assert not _differences(first, second), _differences(first, second)[:20]


BROKEN = """
import dataclasses, sys
from mcillum.validation import cli
from mcillum.validation.plan import profiles
# a scene run whose $-parameter the scene does not declare: loading it fails
profiles.PROFILES["quick"] = dataclasses.replace(
    profiles.QUICK, failures=(),
    runs=(profiles.SceneRun(scene="cap_plane", res=4, ladder=(4,), renders=2, max_depth=2,
                            defines={"no_such": 1}),))
sys.exit(cli.main(sys.argv[1:]))
"""

FAILING_JOB = """
import json, sys
import mcillum
from mcillum import errors
from mcillum.validation.plan import scenes
from mcillum.validation import pipeline
from mcillum.validation.run import executors, jobs, renders
variant = renders.set_variant()
broken = jobs.Job(jobs.SceneSpec(sys.argv[1], (), "broken"), jobs.Integrator("path", ()), 1, 0)
# a plugin's own error, which mi.render wraps: a hemisphere estimator and a point light
info = scenes.index()["point_light"]
lit = jobs.SceneSpec(info.path, tuple(sorted(renders.resolve_defines(info.path, res=4).items())),
                     "point_light")
refused = jobs.Job(lit, jobs.Integrator("cosine_hemisphere", (("max_depth", 2),)), 1, 0)

def attempt(executor, job):
    try:
        executor.render([job])
    except Exception as err:
        return [type(errors.root_cause(err)).__name__, errors.message(err)]
    return None

here = [attempt(executors.Local(), job) for job in (broken, refused)]
with pipeline.start_executor("ray", None, 2, variant) as executor:
    there = [attempt(executor, job) for job in (broken, refused)]
print(json.dumps([here, there]))
"""


def test_a_failing_render_fails_the_run_as_it_would_locally(tmp_path):
    """A scene that does not load: the run stops with the same message and
    exit code under both executors (the driver finds it, loading the scene
    to plan the run); and on a worker, a job whose scene file is broken and
    one whose estimator refuses the scene (a plugin error that Mitsuba wraps)
    raise what they raise in this process, with the message the command
    prints."""
    runs = {}
    for kind in ("local", "ray"):
        proc = subprocess.run(
            [sys.executable, "-c", BROKEN, "validate", "--no-speed", "--executor", kind,
             "--out", str(tmp_path / kind), "--cache", str(tmp_path / "cache")],
            capture_output=True, text=True, timeout=300)
        # the message: from its first line to the end (Ray may warn before it,
        # e.g. of a small /dev/shm in a container)
        start = proc.stderr.find("mcillum validate: error:")
        runs[kind] = proc.returncode, proc.stderr[start:] if start >= 0 else proc.stderr
        assert "Traceback" not in proc.stderr and "RayTaskError" not in proc.stderr, proc.stderr
    assert runs["local"][0] == runs["ray"][0] == 1
    assert runs["local"][1] == runs["ray"][1], runs
    assert runs["local"][1].startswith("mcillum validate: error:") and "no_such" in runs["local"][1]

    broken = tmp_path / "broken.xml"
    files.write_text(str(broken), '<scene version="3.0.0"><shape type="sphere"></scene>\n')
    proc = subprocess.run([sys.executable, "-c", FAILING_JOB, str(broken)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    here, there = json.loads(proc.stdout.strip().splitlines()[-1])
    assert None not in here and here == there             # what the CLI would print
    assert here[1][0] == "UnreachableContentError" and "point" in here[1][1].lower()
    assert all("Ray" not in m and "Traceback" not in m for _, m in there)
