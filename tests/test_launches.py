"""Renders as tiles of one launch (validation/run/launches.py): each tile must
be distributed as a render launched alone, in its own place, and the suite
must launch alone what cannot be tiled."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

from conftest import SCENES
from mcillum.validation.run import jobs, launches, renders


def _scene(name, res=8, **defines):
    return renders.load_scene(str(SCENES / f"{name}.xml"), res=res, **defines)


def _stack(outs):
    return np.stack([o.image[..., :3] for o in outs]).astype(np.float64)


def _welch_z(a, b):
    """Per-pixel Welch z of two stacks (K, H, W, C) of independent renders."""
    va, vb = a.var(0, ddof=1) / len(a), b.var(0, ddof=1) / len(b)
    se = np.sqrt(va + vb)
    return np.where(se > 0, (a.mean(0) - b.mean(0)) / np.where(se > 0, se, 1), 0.0)


# --------------------------------- Arithmetic ---------------------------------

def test_per_launch_fills_up_to_the_lane_cap():
    assert launches.per_launch(64, 16, max_lanes=1 << 20) == 1024
    assert launches.per_launch(64, 2048, max_lanes=1 << 20) == 8
    # a render larger than the cap is launched alone
    assert launches.per_launch(128 * 128, 256, max_lanes=1 << 20) == 1


def test_launch_seeds_differ_for_other_seed_lists():
    seen = {launches.launch_seed(tuple(range(a, a + k))) for a in range(50) for k in (2, 8, 64)}
    assert len(seen) == 150
    assert launches.launch_seed((3, 4)) != launches.launch_seed((4, 3))
    assert all(0 <= s < 2 ** 32 for s in seen)


def test_tile_takes_columns_in_order():
    image = np.arange(2 * 12 * 1, dtype=np.float32).reshape(2, 12, 1)
    assert launches.tile(image, 3, 1)[..., 0].tolist() == [[4, 5, 6, 7], [16, 17, 18, 19]]


# ------------------------------- Distribution ---------------------------------

@pytest.mark.parametrize("name, case", [("path", "cornell_box"),
                                        ("bayesian_hemisphere", "lone_sphere")])
def test_tiles_are_distributed_as_lone_renders(name, case):
    """Per pixel, 48 tiles against 48 lone renders: the Welch z of every
    pixel and channel is standard normal (a tile in the wrong place, a
    filter that splats across tiles or tiles that share samples would not
    be). Bayesian_hemisphere also carries AOVs, which are tiled alike."""
    defines = {"envmap": "sg"} if case == "lone_sphere" else {}
    scene = _scene(case, **defines)
    made = renders.make_integrator(name, {"max_depth": 2} if case == "lone_sphere" else {})
    k, spp = 48, 64
    lone = [renders.render(scene, made, spp, 10_000 + s) for s in range(k)]
    tiles = launches.render(scene, made, spp, 777, tuple(range(k)))
    assert [t.seed for t in tiles] == list(range(k))
    assert {t.image.shape for t in tiles} == {lone[0].image.shape}
    z = _welch_z(_stack(tiles), _stack(lone)).ravel()
    z = z[z != 0]
    # (Welch z with 47 dof per side: t-like tails, so bounds from the t)
    assert np.mean(np.abs(z) > 3) < 0.03
    assert np.max(np.abs(z)) < stats.t.ppf(1 - 1e-4 / len(z), 47)
    assert abs(np.mean(z ** 2) - 1) < 0.35
    # tiles are independent of one another: no two equal
    flat = _stack(tiles).reshape(k, -1)
    assert len({row.tobytes() for row in flat}) == k
    for group in lone[0].aovs:
        a = np.stack([t.aovs[group] for t in tiles]).mean(0)
        b = np.stack([r.aovs[group] for r in lone]).mean(0)
        assert a.shape == b.shape
        assert np.allclose(a.mean(), b.mean(), rtol=0.1)
    # the launch's time is shared out, and says so
    assert all(t.meta["launch"]["tiles"] == k for t in tiles)
    assert math.isclose(sum(t.seconds for t in tiles), tiles[0].seconds * k)


def test_a_tile_in_the_wrong_place_is_seen():
    """The distribution test above can fail: tiles mirrored left-right
    (each tile's pixels in the wrong place) are rejected."""
    scene = _scene("cornell_box")
    made = renders.make_integrator("path", {})
    k, spp = 48, 64
    lone = _stack([renders.render(scene, made, spp, 10_000 + s) for s in range(k)])
    tiles = _stack(launches.render(scene, made, spp, 777, tuple(range(k))))[:, :, ::-1]
    z = _welch_z(tiles, lone).ravel()
    assert np.mean(np.abs(z) > 3) > 0.2


# --------------------------------- Grouping -----------------------------------

def _jobs(scene, name, spp, seeds, params=None):
    spec = jobs.SceneSpec("x.xml", (), "key")
    integrator = jobs.make(name, params or {})
    return [jobs.Job(spec, integrator, spp, s, live=scene) for s in seeds]


def test_grouped_puts_one_integrator_and_spp_in_a_launch_and_ungroups_in_order():
    scene = _scene("cornell_box")
    batch = []
    for i in range(4):     # interleaved, as stacks.interleaved orders them
        batch += _jobs(scene, "path", 16, [i]) + _jobs(scene, "cosine_hemisphere", 16, [i])
    batch += _jobs(scene, "path", 1 << 15, [5, 6, 7])     # 2²¹ lanes each: alone
    batch += _jobs(scene, "cosine_hemisphere", 1 << 13, [8, 9, 10])    # 2 a launch
    launched, slots = launches.grouped(batch)
    assert [len(s) for s in slots] == [4, 4, 1, 1, 1, 2, 1]
    assert slots[0] == [0, 2, 4, 6] and slots[1] == [1, 3, 5, 7]
    assert launched[0].seeds == (0, 1, 2, 3)
    assert launched[0].seed == launches.launch_seed((0, 1, 2, 3))
    # a launch of one is that job, with its own seed
    assert [(j.seed, j.seeds) for j in launched[2:5]] == [(5, ()), (6, ()), (7, ())]
    assert launched[5].seeds == (8, 9) and (launched[6].seed, launched[6].seeds) == (10, ())
    back = launches.ungrouped([["p0", "p1", "p2", "p3"], ["c0", "c1", "c2", "c3"], "a", "b",
                               "c", ["d", "e"], "f"], slots)
    assert back == ["p0", "c0", "p1", "c1", "p2", "c2", "p3", "c3", "a", "b", "c", "d", "e", "f"]


def test_grouped_launches_alone_what_cannot_be_tiled(tmp_path):
    scene = _scene("cornell_box")
    learner = _jobs(scene, "guided_path", 16, range(4))
    launched, _ = launches.grouped(learner)
    assert len(launched) == 4 and not any(j.seeds for j in launched)
    assert launches.integrator_refusal(learner[0].integrator) == "it learns within a launch"

    gaussian = mi.load_string("""<scene version="3.0.0">
        <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
        <integer name="height" value="8"/></film></sensor>
        <shape type="sphere"/><emitter type="constant"/></scene>""")
    assert "GaussianFilter" in launches.scene_refusal(gaussian)
    launched, _ = launches.grouped(_jobs(gaussian, "path", 16, range(4)))
    assert len(launched) == 4
    stratified = mi.load_string("""<scene version="3.0.0">
        <sensor type="perspective"><sampler type="stratified"/>
        <film type="hdrfilm"><rfilter type="box"/></film></sensor></scene>""")
    assert "not independent" in launches.scene_refusal(stratified)
    assert launches.scene_refusal(scene) is None


def test_a_user_class_that_replaces_render_is_launched_alone():
    class Own(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)

        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            return super().render(scene, sensor, seed, spp, develop, evaluate)

    class OnlySample(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)

    props = mi.Properties()
    own = jobs.Integrator("own_render", (), Own(props))
    plain = jobs.Integrator("only_sample", (), OnlySample(props))
    assert launches.integrator_refusal(own) == "its class replaces render()"
    assert launches.integrator_refusal(plain) is None
    assert launches.integrator_refusal(jobs.make("path", {})) is None
    assert launches.integrator_refusal(jobs.make("cosine_hemisphere", {})) is None
