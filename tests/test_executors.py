"""Where renders run (validation/run/jobs.py, executors.py), without Ray: a job
that travels rebuilds the same image, a node without the scene's files renders
it from a copy, the reference does not depend on how many passes an executor
renders at once, timed renders are the ones whose times are reported, and
``--executor ray`` without Ray says how to install it. With Ray: test_ray.py."""

from __future__ import annotations

import os
import pickle
import sys

import numpy as np
import pytest

from mcillum.validation import cli, pipeline
from mcillum.validation.plan import profiles
from mcillum.validation.run import executors, jobs, references
from mcillum.validation.stages import common, sequential
from mcillum.validation.stages.context import Context, Run


def _context(tmp_path, scene="lone_sphere", defines=None, res=8) -> Context:
    """A loaded scene as a validation context (lone_sphere under the
    generated sg map: an absolute path into the cache)."""
    defines = {"envmap": "sg"} if defines is None else defines
    profile = profiles.Profile(name="test", runs=())
    plan = profiles.SceneRun(scene=scene, res=res, ladder=(4,), renders=2, max_depth=2,
                             defines=defines)
    ctx = Context(Run(profile, "llvm_ad_rgb", str(tmp_path / "cache"), str(tmp_path / "out")),
                  plan, scene, ["cosine_hemisphere"], dict(plan.defines))
    common.load(ctx)
    return ctx


def test_a_job_travels_without_its_objects_and_renders_the_same(llvm, tmp_path):
    ctx = _context(tmp_path)
    job = ctx.job(jobs.make("cosine_hemisphere", ctx.params), 16, 7)
    here = executors.Local().render([job])[0]
    sent = pickle.loads(pickle.dumps(job))
    assert sent.live is None and sent.integrator.made is None
    assert (sent.scene, sent.integrator, sent.spp, sent.seed) == \
        (job.scene, job.integrator, job.spp, job.seed)
    there = executors.Local().render([sent])[0]            # rebuilt from the names
    assert np.array_equal(here.image, there.image)
    other = executors.Local().render([jobs.Job(job.scene, job.integrator, 16, 8)])[0]
    assert not np.array_equal(here.image, other.image)     # (the seed decides)


def test_a_timed_render_that_compiled_is_rendered_again(llvm):
    """renders.timed_render: a render that compiled a kernel took the
    compiler's time, so it is rendered again and the second kept, with the
    same image; a warm render is rendered once. Dr.Jit's kernel history is
    left as it was."""
    import drjit as dr
    import mitsuba as mi

    from mcillum.validation.run import renders

    class Constant(mi.SamplingIntegrator):
        # (a literal no earlier kernel holds: this one compiles)
        value = float(np.random.default_rng().uniform(1.0, 2.0))

        def sample(self, scene, sampler, ray, medium=None, active=True):
            return mi.Spectrum(self.value) * sampler.next_1d(), True, []

    scene = mi.load_dict({"type": "scene", "sensor": {
        "type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4,
                                        "rfilter": {"type": "box"}}}})
    integrator = Constant(mi.Properties())
    first = renders.timed_render(scene, integrator, 3, seed=1)
    assert first.meta.get("compile_seconds", 0) > 0        # (the render set aside)
    assert np.array_equal(first.image, renders.render(scene, integrator, 3, seed=1).image)
    warm = renders.timed_render(scene, integrator, 3, seed=2)
    assert "compile_seconds" not in warm.meta
    assert (first.first_seconds, warm.first_seconds) == (first.meta["compile_seconds"],
                                                         warm.seconds)
    assert not np.array_equal(first.image, warm.image)     # (the seed decides)
    assert not dr.flag(dr.JitFlag.KernelHistory)


#: A user's scene with a Gaussian reconstruction filter (radius 2 px) over a
#: checkerboard: a pixel's value takes samples from its neighbours' area.
EDGE = """<scene version="3.0.0">
    <default name="res" value="16"/>
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    <sensor type="orthographic">
        <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm"><integer name="width" value="$res"/>
            <integer name="height" value="$res"/><rfilter type="gaussian"/></film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
    <shape type="rectangle">
        <transform name="to_world"><scale value="0.5"/></transform>
        <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
            <rgb name="color0" value="0.05"/><rgb name="color1" value="0.9"/>
            <transform name="to_uv"><scale value="3"/></transform></texture></bsdf>
    </shape>
</scene>
"""


def test_path_beside_a_confirmation_renders_windows_around_the_pixels_read(llvm, tmp_path):
    """Where only some pixels' rejections came back, path is rendered in
    windows around them (a cropped film, through a job that travels) with
    the filter's reach around each: there it agrees with path on the whole
    film. A window's own edge pixels do not (they miss the samples of
    neighbours outside): without the border, the pixels read would be those."""
    scene = tmp_path / "edge.xml"
    scene.write_text(EDGE)
    ctx = _context(tmp_path, str(scene), {}, res=16)
    ctx.id = "edge"                                 # (as a scene file's run names it)
    ctx.integrators = {"path": jobs.make("path", ctx.params)}
    control = sequential.control_renderer(ctx, "cosine_hemisphere")
    pixels = np.zeros((16, 16), bool)
    pixels[5, 6] = pixels[10, 9] = True
    assert common.windows(pixels, 2) == [(4, 3, 5, 5), (7, 8, 5, 5)]
    k, spp = 16, 1024
    whole = control(1, spp, k)[1]
    around = np.full_like(whole, -1.0)
    part = control(1, spp, k, pixels, around)[1]
    inside = np.zeros((16, 16), bool)
    inside[3:8, 4:9] = inside[8:13, 7:12] = True
    assert np.all(part[:, ~inside] == -1.0) and np.all(part[:, inside] >= 0.0)
    t = np.abs(whole.mean(0) - part.mean(0)) / np.sqrt(
        (whole.var(0, ddof=1) + part.var(0, ddof=1)) / k + 1e-30)
    assert t[pixels].max() < 4, t[pixels]
    edges = inside.copy()
    edges[4:7, 5:8] = edges[9:12, 8:11] = False
    assert t[edges].max() > 6, t[edges]            # measured: 30-100
    files = os.listdir(os.path.join(ctx.run.out_dir, "renders", ctx.id))
    assert sum("-crop" in f for f in files) == 2, files
    # a window's job travels: a worker loads the same window (jobs.Workshop)
    job = common.cropped(ctx, (4, 3, 5, 5)).job(ctx.integrators["path"], 16, 7)
    here = executors.Local().render([job])[0]
    there = executors.Local().render([pickle.loads(pickle.dumps(job))])[0]
    assert here.image.shape[:2] == (5, 5) and np.array_equal(here.image, there.image)
    # a film with a crop window of its own (a user's scene file as a failure
    # case): its pixels are that window's, and path renders it whole
    own = tmp_path / "own.xml"
    own.write_text(EDGE.replace('<rfilter type="gaussian"/>', '<rfilter type="gaussian"/>'
                                '<integer name="crop_offset_x" value="2"/>'
                                '<integer name="crop_width" value="12"/>'))
    ctx = _context(tmp_path, str(own), {}, res=16)
    ctx.id = "own"
    ctx.integrators = {"path": jobs.make("path", ctx.params)}
    around = np.full((2, 16, 12, 3), -1.0)
    control = sequential.control_renderer(ctx, "cosine_hemisphere")
    got = control(1, 16, 2, pixels[:, :12], around)[1]
    assert got.shape == around.shape and np.all(got >= 0.0)
    # asked first, far past the reference (sequential.PATH_FIRST), path
    # renders windows or nothing: the whole film is the estimator's batch's cost
    assert control(1, 16, 2, pixels[:, :12], around, True) is None


@pytest.mark.parametrize("scene, defines", [("lone_sphere", {"envmap": "sg"}),
                                             ("sky_sphere", {})])
def test_a_node_without_the_files_renders_from_a_copy(llvm, tmp_path, monkeypatch, scene,
                                                     defines):
    """Another machine: the scene file, its includes and the map are not at
    the driver's paths there (a generated map is a file in the driver's
    cache, given by absolute path; sky_sphere's default map is given as
    scenes/../envmaps/…, not normalised)."""
    monkeypatch.setenv("MCILLUM_CACHE", str(tmp_path / "node-cache"))
    ctx = _context(tmp_path, scene, defines)
    spec, integrator = ctx.scene_spec, jobs.make("cosine_hemisphere", ctx.params)
    content = jobs.scene_files(spec)
    envmap = dict(spec.defines)["envmap"]
    assert spec.path in content and os.path.abspath(envmap) in content
    elsewhere = "/no-such-node-dir"

    def moved(path):
        return elsewhere + path

    # what a driver elsewhere sends: its own paths, as it has them
    far = jobs.SceneSpec(moved(spec.path), tuple(
        (k, moved(v) if os.path.isabs(v) and os.path.exists(v) else v)
        for k, v in spec.defines), spec.key)
    shop = jobs.Workshop()
    out = shop.run(jobs.Job(far, integrator, 16, 3),
                   lambda: {moved(p): data for p, data in content.items()})
    assert shop.copied == [spec.key] and not os.path.exists(elsewhere)
    assert os.path.isdir(tmp_path / "node-cache" / "scene_copies" / spec.key)
    here = jobs.Workshop()
    same = here.run(jobs.Job(spec, integrator, 16, 3), lambda: content)
    assert here.copied == []                                 # its own files: no copy
    assert np.array_equal(out.image, same.image)


class _Wide(executors.Local):
    """This process, claiming to render several passes at once (batches as a
    Ray run of that many workers makes them)."""

    def __init__(self, parallelism):
        super().__init__()
        self.parallelism = parallelism
        self.batches = []

    def render(self, batch, progress=None, timed=False):
        self.batches.append(len(batch))
        return super().render(batch, progress, timed)


def _reference(tmp_path, executor, targets):
    profile = profiles.Profile(name="test", runs=(), reference_spp_per_pass=16,
                               reference_max_spp=1 << 24)
    plan = profiles.SceneRun(scene="furnace_sphere", res=4, ladder=(1,), renders=2, max_depth=2)
    ctx = Context(Run(profile, "llvm_ad_rgb", str(tmp_path), str(tmp_path / "out"),
                      executor=executor), plan, "furnace_sphere", ["path"])
    common.load(ctx)
    out = []
    for target in targets:
        out.append(references.ensure(ctx, target(out)))
    return out


def test_the_reference_does_not_depend_on_the_batch(llvm, tmp_path):
    """Passes are folded one at a time and the rules read after each: a
    first reference (MIN_PASSES), then one extended to a quarter of its
    variance, are the same with one pass at a time and with batches of 5
    (which render passes beyond the stopping point and drop them)."""
    targets = [lambda _: 1.0, lambda out: float(out[0].variance_of_mean.mean()) / 4]
    one = _reference(tmp_path / "one", executors.Local(), targets)
    wide = _Wide(5)
    five = _reference(tmp_path / "five", wide, targets)
    assert max(wide.batches) > 1 and sum(wide.batches) > five[-1].passes   # some dropped
    for a, b in zip(one, five):
        assert a.passes == b.passes and a.passes >= references.MIN_PASSES
        assert np.array_equal(a.mean, b.mean) and np.array_equal(a.m2, b.m2)
        assert np.array_equal(a.image_means, b.image_means)
    assert one[1].passes > one[0].passes


class _Recording(executors.Local):
    """This process, noting of every batch whether it was timed, and its scene."""

    def __init__(self):
        super().__init__()
        self.calls = []

    def render(self, batch, progress=None, timed=False):
        self.calls.append((timed, {j.scene.key for j in batch}, len(batch)))
        return super().render(batch, progress, timed)


def test_the_renders_whose_times_are_reported_are_timed(llvm, tmp_path):
    """A scene comparison with its speed stage: every render at the display
    resolution (cost model, budgets) is in a timed batch, the ladder's are not
    (but the compile renders, whose seconds are reported, are), and the
    result names the node that timed them."""
    recorder = _Recording()
    profile = profiles.Profile(name="test", runs=(), reference_max_seconds=10.0)
    plan = profiles.SceneRun(scene="furnace_sphere", res=4, ladder=(4, 16), renders=2,
                             max_depth=2, display=profiles.Display(res=32, path_spp=(4, 16),
                                                                   renders=2, repeats=2))
    run = Run(profile, "llvm_ad_rgb", str(tmp_path / "cache"), str(tmp_path / "out"),
              executor=recorder)
    result, _ = pipeline.compare_scene(run, plan, ["cosine_hemisphere", "path"])
    small = Context(run, plan, plan.id, [])
    common.load(small)
    display = {k for _, keys, _ in recorder.calls for k in keys} - {small.scene_key}
    assert len(display) == 1                                  # the 32² scene
    flags = {key: [timed for timed, keys, _ in recorder.calls if keys == {key}]
             for key in (small.scene_key, *display)}
    # compile, then two rungs and the reference's passes (one at a time here)
    ladder = flags[small.scene_key]
    assert ladder[0] and not any(ladder[1:]) and len(ladder) >= 4
    # pilot, timing plan, two budgets (and any corrections toward them);
    # then the display reference
    speed = flags[display.pop()]
    timed = speed.index(False)
    assert timed >= 4 and not any(speed[timed:]), speed
    assert result.speed.timed_on == [executors.node_name()]


def test_executor_ray_without_ray_says_how_to_install_it(llvm, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)              # import ray fails
    monkeypatch.delitem(sys.modules, "mcillum.validation.run.ray_executor", raising=False)
    code = cli.main(["validate", "--executor", "ray", "--scenes", "cap_plane", "--no-speed",
                     "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == cli.EXIT_FAILED and len(err) == 1, err
    assert "pip install 'mcillum[ray]'" in err[0] and "Traceback" not in err[0]


@pytest.mark.parametrize("argv, says", [
    (["--ray-address", "auto"], "--ray-address and --ray-workers need --executor ray"),
    (["--ray-workers", "2"], "--ray-address and --ray-workers need --executor ray"),
    (["--executor", "ray", "--ray-workers", "0"], "--ray-workers must be >= 1"),
    (["--executor", "dask"], "invalid choice: 'dask'")])
def test_ray_options_are_checked(argv, says, capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["validate", "--out", str(tmp_path), *argv])
    assert exit_.value.code == cli.EXIT_USAGE
    assert says in capsys.readouterr().err


def test_unknown_executor_kind():
    with pytest.raises(ValueError, match="unknown executor 'dask'"):
        pipeline.start_executor("dask")


def test_ray_is_an_optional_extra():
    """pyproject pins Ray in the `ray` extra (a 2.x minor), not in the
    dependencies, and declares the `ray` test marker."""
    import tomllib
    with open(os.path.join(os.path.dirname(__file__), "..", "pyproject.toml"), "rb") as f:
        project = tomllib.load(f)
    deps = project["project"]
    assert not any(d.startswith("ray") for d in deps["dependencies"])
    pins = deps["optional-dependencies"]["ray"]
    assert len(pins) == 1 and pins[0].startswith("ray==2.") and pins[0].endswith(".*")
    markers = project["tool"]["pytest"]["ini_options"]["markers"]
    assert any(m.startswith("ray:") for m in markers)


def test_scene_files_go_once_and_the_last_few_stay(monkeypatch):
    """Each scene's files are put into Ray's object store once; a call gets
    the files of every scene of its batch, even of more scenes than the store
    keeps; afterwards the last FILES_KEPT scenes stay (without Ray: `ray.put`
    replaced by a counter)."""
    pytest.importorskip("ray", reason="Ray is not installed: pip install -e '.[ray]'")
    from mcillum.validation.run import ray_executor
    put = []
    monkeypatch.setattr(ray_executor.ray, "put", lambda files: put.append(files) or files)
    monkeypatch.setattr(jobs, "scene_files", lambda spec: f"files of {spec.key}")
    executor = object.__new__(ray_executor.RayExecutor)
    executor._files = ray_executor.OrderedDict()
    kept = ray_executor.FILES_KEPT

    def batch(*keys):
        return [jobs.Job(jobs.SceneSpec(f"{k}.xml", (), k), jobs.Integrator("path", ()), 1, 0)
                for k in keys]

    many = [f"s{i}" for i in range(kept + 2)]           # s0 … s5 with 4 kept
    assert executor._files_of(batch(*many, "s0")) == {k: f"files of {k}" for k in many}
    assert len(put) == len(many)                        # s0 once in its batch
    assert list(executor._files) == [*many[-kept + 1:], "s0"]   # s3 s4 s5 s0
    executor._files_of(batch("s3"))                     # used again: kept longest
    assert len(put) == len(many)
    executor._files_of(batch("new"))
    assert len(put) == len(many) + 1
    assert list(executor._files) == ["s5", "s0", "s3", "new"]
