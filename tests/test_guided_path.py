"""guided_path: its learned density matches its samples, learning finds the
light a scene hides, the image stays unbiased whatever was learned, and a
wrong learned pdf in the weight is caught. (Its agreement with `path` on the
bundled scenes and its BSDF- and emitter-weight twins run with every other
estimator's: test_agreement.py, test_analytic.py, test_plugins.py, ….)"""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from mcillum.testing import assert_unbiased, compare
from mcillum.validation.run import renders

from conftest import SCENES, batch, disk, tiny_scene

ROOM = str(SCENES / "sunlit_room.xml")


def gp():
    """The plugin module, bound to the current variant."""
    from mcillum.integrators.guiding import guided_path
    return guided_path


def guide():
    """What the plugin learns and samples from (integrators/guiding/, every
    module but the plugin's), as one namespace."""
    import types
    from mcillum.integrators.guiding import (directional, guide, moments, records, spatial,
                                             tables, trainer)
    out = types.SimpleNamespace()
    for module in (spatial, tables, directional, records, guide, moments, trainer):
        out.__dict__.update({k: v for k, v in vars(module).items() if not k.startswith("__")})
    return out


def random_guide(res, rows=3, seed=1, peak=20.0):
    """The device tables of ``rows`` random pmfs over res² cells, the second
    with a cell ``peak``× the others. (A peak of 200, 80 % of the mass in
    one cell, is rejected by χ² even at ires 16: its curved edges are
    integrated too roughly.)"""
    rng = np.random.default_rng(seed)
    pmf = rng.random((rows, res * res)) + 0.25
    pmf[1, 5] = peak
    pmf /= pmf.sum(axis=1, keepdims=True)
    tables = guide().guide_tables(pmf)
    return (mi.Float(tables["pmf"]), mi.UInt32(tables["slot"]), mi.UInt32(tables["first"]),
            pmf)


# ------------------------- Sampling the learned part -------------------------

@pytest.mark.parametrize("factor", [1.0, 1.05])
def test_chi2_on_a_learned_density(llvm, factor, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)          # mi.chi2 writes chi2_data.py on rejection
    m, res = gp(), 8
    pmf, slot, _, _ = random_guide(res)
    row = mi.UInt32(1)                   # the second row

    def sample(u):
        w, _ = m.sample_guide(slot, row, res, u.x, mi.Point2f(u.y, u.z))
        return w

    def pdf(w):
        return factor * m.guide_pdf(pmf, row, res, w)

    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample,
                                 pdf_func=pdf, sample_dim=3, sample_count=1_000_000,
                                 res=101, ires=16)
    # (ires 16: the density jumps at the cells' curved edges, and 4 points per
    # χ² cell integrate it too roughly: a correct density was rejected)
    assert test.run(0.01) == (factor == 1.0), test.messages


def test_inverse_undoes_sampling_and_the_pdf_integrates_to_one(llvm):
    m, res = gp(), 8
    pmf, slot, first, _ = random_guide(res)
    row = mi.UInt32(1)
    rng = mi.PCG32(size=100_000)
    u1, u2 = rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32())
    w, cell = m.sample_guide(slot, row, res, u1, u2)
    v1, v2 = m.invert_guide(first, pmf, row, res, w)
    w2, cell2 = m.sample_guide(slot, row, res, v1, v2)
    assert np.array_equal(np.array(cell), np.array(cell2))
    assert np.max(np.abs(np.array(w) - np.array(w2))) < 1e-3
    # (uniform directions on the sphere: E[p] · 4π = ∫ p; the row without a peak)
    wu = mi.warp.square_to_uniform_sphere(u2)
    integral = float(dr.mean(m.guide_pdf(pmf, mi.UInt32(0), res, wu))[0]) * 4 * np.pi
    assert abs(integral - 1) < 0.02


# ---------------------- Seen from an anchor (parallax) ----------------------

#: A vertex off its anchor, and the learned distance of the light.
X, ANCHOR, DISTANCE = (0.3, -0.2, 0.1), (0.0, 0.0, 0.0), 1.0


@pytest.mark.parametrize("factor", [1.0, 1.05])
def test_chi2_on_a_learned_density_seen_from_an_anchor(llvm, factor, tmp_path, monkeypatch):
    """A vertex draws ω_c from the learned pmf, then ω towards the sphere's
    point: its density is the pmf's at ω_c times dω_c/dω (to_anchor)."""
    monkeypatch.chdir(tmp_path)
    m, res = gp(), 8
    pmf, slot, _, _ = random_guide(res)
    row, x, c, d = mi.UInt32(1), mi.Point3f(*X), mi.Point3f(*ANCHOR), mi.Float(DISTANCE)

    def sample(u):
        w_c, _ = m.sample_guide(slot, row, res, u.x, mi.Point2f(u.y, u.z))
        return m.from_anchor(x, w_c, c, d)

    def pdf(w):
        w_c, jacobian = m.to_anchor(x, w, c, d)
        return factor * m.guide_pdf(pmf, row, res, w_c) * jacobian

    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample,
                                 pdf_func=pdf, sample_dim=3, sample_count=1_000_000,
                                 res=101, ires=16)
    assert test.run(0.01) == (factor == 1.0), test.messages


def test_the_anchor_map_is_undone_and_falls_back_where_nothing_was_learned(llvm):
    """to_anchor inverts from_anchor; a vertex farther from its anchor than
    half the distance maps through a sphere twice as far (it stays inside);
    with no distance learned (0), ω_c = ω and the Jacobian is 1."""
    m = gp()
    rng = mi.PCG32(size=10_000)
    w_c = mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
    c = mi.Point3f(*ANCHOR)
    for x, d in ((X, DISTANCE), ((0.8, 0.1, 0.0), DISTANCE)):
        x = mi.Point3f(*x)
        w = m.from_anchor(x, w_c, c, mi.Float(d))
        back, jacobian = m.to_anchor(x, w, c, mi.Float(d))
        assert np.max(np.abs(np.array(back) - np.array(w_c))) < 1e-4
        assert np.all(np.array(jacobian) > 0)
    same, one = m.to_anchor(mi.Point3f(*X), w_c, c, mi.Float(0.0))
    assert np.array_equal(np.array(same), np.array(w_c)) and np.all(np.array(one) == 1)


def test_records_of_one_small_source_fall_in_one_cell_seen_from_their_anchor(llvm):
    """Vertices spread over one anchor block of a wall, each lit by the same
    point: seen from the anchor, their records share a cell; seen from each
    vertex (parallax off), they spread over many."""
    g, res = guide(), 32
    grid = (np.zeros(3), np.full(3, g.GRID / 4.0))         # a 4-unit cube, 8 per unit
    rng = np.random.default_rng(3)
    n = 2000
    # (the wall z = 0.1, x and y in the first anchor block [0, 1)²)
    px, py = rng.uniform(0.02, 0.98, n), rng.uniform(0.02, 0.98, n)
    x = mi.Point3f(px, py, np.full(n, 0.1))
    voxel = g.voxel_of(x, grid)
    y = mi.Point3f(np.full(n, 2.5), np.full(n, 1.5), np.full(n, 1.2))
    normal = mi.Vector3f(np.zeros(n), np.zeros(n), np.ones(n))
    cells = {}
    for parallax in (True, False):
        cell, _, above = g.anchored_cell(voxel, x, y, normal, grid, res, parallax)
        assert np.all(np.array(above))
        cells[parallax] = len(np.unique(np.array(cell)))
    assert cells[True] == 1 and cells[False] > 10, cells


def test_the_slots_follow_the_pmf_and_miss_no_cell(llvm):
    """Every row's slots: S = 8 per cell in all, each cell at least one,
    the quantized pmf within one slot of the learned one."""
    res = 8
    pmf_q, slot, first, pmf = random_guide(res, peak=200.0)
    n, slots = res * res, guide().SLOTS_PER_CELL * res * res
    counts = np.array(pmf_q).reshape(3, n) * slots
    assert np.allclose(counts, np.round(counts)) and (np.round(counts) >= 1).all()
    assert np.allclose(counts.sum(axis=1), slots)
    assert np.abs(counts - pmf * (slots - n) - 1).max() <= 1 + 1e-6
    cells = np.array(slot).reshape(3, slots)
    for r in range(3):
        assert np.array_equal(np.bincount(cells[r], minlength=n), np.round(counts[r]))


def test_training_passes_double_and_stay_within_their_share(llvm):
    assert guide().training_passes(3, 0.25) == [] and guide().training_passes(16, 0.0) == []
    for spp in (4, 16, 64, 100, 1000):
        passes = guide().training_passes(spp, 0.25)
        assert 1 <= len(passes) <= guide().PASSES and min(passes) >= 1
        assert sum(passes) == int(0.25 * spp)
        assert all(b >= 2 * a for a, b in zip(passes, passes[1:]))


def test_budget_passes_double_while_the_rest_could_draw_one_twice_as_long(llvm):
    """Müller et al.'s rule: iterations 1, 2, 4, … spp; after each the rest
    of the budget is at least twice it, and one more would break that; at
    most ``passes`` of them; the share trained grows with the budget."""
    budget_passes = guide().budget_passes
    assert budget_passes(1) == budget_passes(2) == [] and budget_passes(3) == [1]
    for spp in (4, 7, 16, 64, 100, 1000, 4096):
        passes = budget_passes(spp)
        assert passes == [2 ** i for i in range(len(passes))]
        assert spp - sum(passes) >= 2 * passes[-1]
        assert spp - sum(passes) - 2 * passes[-1] < 4 * passes[-1]       # (no room for one more)
    assert budget_passes(1000, 3) == [1, 2, 4]
    assert sum(budget_passes(100)) < sum(budget_passes(1000)) < sum(budget_passes(10_000))


def test_each_iteration_weighs_by_its_inverse_variance(llvm):
    """moments.relative_variances on pixels of known spread (per pixel μ in
    0.1-2, one sample's relative variance 0.5, 2 and 1 in three iterations,
    the last of one sample a pixel) finds them; the weights are then ∝ spp / variance, shrunk
    towards ∝ spp for few samples, and ∝ spp where a variance is not a
    positive number."""
    g, rng = guide(), np.random.default_rng(11)
    pixels, mu = 4096, rng.uniform(0.1, 2.0, 4096)

    def moments(spp, rel):
        m = g.PixelMoments()
        for h in (0, 1):
            n = (spp + 1 - h) // 2
            x = mu[:, None] * (1 + np.sqrt(rel) * rng.standard_normal((pixels, n)))
            m.add([(x.sum(axis=1), (x * x).sum(axis=1), n) if k == h else
                   (np.zeros(pixels), np.zeros(pixels), 0) for k in (0, 1)])
        return m
    got = g.relative_variances([moments(8, 0.5), moments(32, 2.0), moments(1, 1.0)])
    weight = mu ** 2 / (mu ** 2 + g.RELATIVE_EPSILON)      # (relMSE's weighing of a pixel)
    # (each within 25 %: the pixels' weight reads a mean of 41 samples a
    # pixel, whose noise raises all three alike, 16 % here; their ratios,
    # which weigh the images, within 5 and 10 %)
    for v, rel in zip(got, (0.5, 2.0, 1.0)):
        assert abs(v / (rel * np.average(weight)) - 1) < 0.25, (got, rel)
    assert abs(got[1] / got[0] / 4 - 1) < 0.05, got
    assert abs(got[2] / got[0] / 2 - 1) < 0.1, got
    many = [1 << 30, 1 << 30]
    w = g.inverse_variance_weights([8, 32], [0.5, 2.0], many)
    assert np.allclose(w, [0.5, 0.5], rtol=1e-3)              # (8/0.5 = 32/2)
    few = g.inverse_variance_weights([8, 32], [0.5, 2.0], [16, 64])
    assert abs(few[0] - 0.2) < 0.01                          # (∝ spp, nearly)
    assert g.inverse_variance_weights([8, 32], [float("nan"), 1.0]) == [0.2, 0.8]


def concentrated_records(res, rng, records=200_000, patch=(5, 6), light=50.0, noise=1.0):
    """Records on a res² square: light ``light`` in one fine cell ``patch``
    (row, column), exponential noise of mean ``noise`` everywhere, records
    uniform over the square; their counts and Σ L_i per cell (1, res²)."""
    cell = rng.integers(0, res * res, records)
    li = rng.exponential(noise, records) + np.where(cell == patch[0] * res + patch[1], light, 0.0)
    hits = np.bincount(cell, minlength=res * res).astype(float)[None]
    return hits, np.bincount(cell, weights=li, minlength=res * res)[None]


def test_the_quadtree_resolves_a_small_bright_cell_and_smooths_the_rest(llvm):
    """Light in one of 32² cells: the refined means put about its share of
    the light in that cell (a flat 8² grid spreads it over 16 cells), and
    the dark cells, each under 1 % of the light, stay at a coarser level
    instead of following each fine cell's noise."""
    res = 32
    hits, total = concentrated_records(res, np.random.default_rng(3))
    means = guide().refined_means(hits, total, res, 0.01)[0].reshape(res, res)
    share = means[5, 6] / means.sum()
    truth = 50 / (50 + res * res * 1.0)
    assert 0.7 * truth < share < 1.3 * truth, (share, truth)
    # (far from the light cells stop at 16² (each holds under 1 % of the
    # light): they vary less than the 32² cells' own means)
    raw = (total / hits)[0].reshape(res, res)
    far = means[16:, 16:]
    assert far.std() < 0.6 * raw[16:, 16:].std() and abs(far.mean() - 1) < 0.1
    # without refinement every cell carries the square's mean
    flat = guide().refined_means(hits, total, res, 1.0)[0]
    assert np.ptp(flat) < 1e-9


def test_a_lone_bright_record_does_not_make_a_spike(llvm):
    """A cell refined on few records is pulled towards its parent's mean
    (SHRINK records' worth): one record 100× the rest raises its cell's
    weight by far less than 100×."""
    res = 32
    rng = np.random.default_rng(5)
    hits, total = concentrated_records(res, rng, records=3000, light=0.0)
    total[0, 7 * res + 7] += 100.0
    means = guide().refined_means(hits, total, res, 0.0)[0]
    assert means.max() / np.median(means) < 10, means.max() / np.median(means)


@pytest.mark.parametrize("params, message", [
    ({"bsdf_fraction": 0.0}, "bsdf_fraction"), ({"train_fraction": 1.0}, "train_fraction"),
    ({"directional_res": 12}, "power of 2"), ({"spatial_threshold": 0}, "spatial_threshold"),
    ({"directional_threshold": 1.0}, "directional_threshold"),
    ({"roulette": "never"}, "roulette")])
def test_bad_parameters_are_refused(llvm, params, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": "guided_path", **params})


# ------------------------------- Learning -----------------------------------

def test_records_added_in_pieces_learn_what_their_sums_say(llvm):
    """guide.Tally: records added in three pieces learn the same tree and
    pmfs as all at once, and every leaf's per-cell count, Σ L_i and Σ L_i²
    are its records' own (summed here by the leaf each voxel lands in).
    The first two pieces outnumber their voxels' cells, so they are folded
    into per-voxel sums (the second into new rows); the third, spread over
    the grid, is kept as it came: the learning reads both."""
    g, res, n = guide(), 8, 60_000
    rng = np.random.default_rng(7)
    voxel = np.concatenate([rng.integers(100, 140, n // 4), rng.integers(200, 260, n // 4),
                            rng.integers(0, g.GRID ** 3, n // 2)])
    cell = rng.integers(0, res * res, n)
    li = rng.exponential(1.0, n) * (rng.random(n) < 0.5)
    ld = rng.exponential(1.0, n) * (rng.random(n) < 0.2)
    whole, pieces = g.Tally(res), g.Tally(res)
    whole.add(voxel, cell, li, ld)
    for a, b in ((0, n // 4), (n // 4, n // 2), (n // 2, n)):
        pieces.add(voxel[a:b], cell[a:b], li[a:b], ld[a:b])
    assert len(pieces._voxels) == 100 and len(pieces._kept) == 1     # (both kinds)
    assert whole.records == pieces.records == n
    one, three = (g.Guide.learn(t, 2.0, 0.01) for t in (whole, pieces))
    assert one.leaves == three.leaves > 8
    assert np.array_equal(one.voxel_node, three.voxel_node)
    assert np.allclose(one.pmf, three.pmf, rtol=1e-12, atol=0)
    leaf = three.voxel_node[voxel]
    for got, w in ((three.counts, None), (three.sums, li), (three.squares, li * li)):
        want = np.bincount(leaf * res * res + cell, weights=w,
                           minlength=len(three.child) * res * res).reshape(-1, res * res)
        leaves = three.child == 0
        assert np.allclose(got[leaves], want[leaves], rtol=1e-12, atol=1e-12)


def pixel_variance(scene, integrator, spp, seeds=12):
    images = batch(scene, integrator, spp, seeds)[..., :3]
    return float(np.mean(images.var(axis=0, ddof=1))), float(images.mean())


def test_what_it_learns_lowers_the_variance_where_light_comes_indirectly(llvm):
    """sunlit_room at 32², direct light and one indirect bounce: with the
    guide learned from 480 spp, the 32 spp that render the image vary less
    than `mis`'s 32 spp (0.71× here; 0.77× with flat 8² cells); their
    means agree."""
    scene = renders.load_scene(ROOM, res=32)
    mis = renders.make_integrator("mis", {"max_depth": 3})
    guided = renders.make_integrator("guided_path", {"max_depth": 3, "train_fraction": 0.9375,
                                                     "train_passes": 2, "combine_passes": False})
    v_mis, mean_mis = pixel_variance(scene, mis, 32)
    v_guided, mean_guided = pixel_variance(scene, guided, 512)
    assert [t["spp"] for t in guided.training] == [160, 320]
    assert guided.training[-1]["trained_leaves"] > 1
    assert v_guided < 0.9 * v_mis, (v_guided, v_mis)
    assert abs(mean_guided / mean_mis - 1) < 0.05


def test_roulette_that_reads_the_unguided_weight_keeps_the_paths_towards_the_light(llvm):
    """sunlit_room under its hole at 32² × 512 spp (roulette from depth 5 in
    a white room): roulette on the larger of the weight and the BSDF's
    leaves the pixels' relative variance below roulette on the weight alone
    (0.83-0.87× here; 0.55× in relMSE at 64² × 1 024 spp), the means
    agreeing."""
    scene = renders.load_scene(ROOM, res=32, gap="hole", sun=500)
    found = {}
    for roulette in ("unguided", "throughput"):
        # (every density kept: a guided pass at 32² that measures no gain
        # would render the rest as mis, and roulette is what is tested)
        guided = renders.make_integrator("guided_path", {"roulette": roulette,
                                                         "max_variance_ratio": 1e30})
        images = batch(scene, guided, 512, 6)[..., :3]
        mean = images.mean(axis=0)
        found[roulette] = (float(np.mean(images.var(axis=0, ddof=1)
                                         / np.maximum(mean, 1e-3) ** 2)), float(mean.mean()))
    assert found["unguided"][0] < 0.95 * found["throughput"][0], found
    assert abs(found["unguided"][1] / found["throughput"][1] - 1) < 0.05, found

def test_where_light_is_mostly_direct_the_bsdf_takes_the_larger_share(llvm):
    """sky_sphere (a smooth sky, little light arriving indirectly): the BSDF's
    share of the mixture grows with the direct share, and the variance stays
    near `mis`'s (1.09× at 24² here; 2.3× with the fixed share 0.5, which
    this bound rejects). In sunlit_room's walls all light is indirect: the
    share stays near ``bsdf_fraction``."""
    sky = renders.load_scene(str(SCENES / "sky_sphere.xml"), res=24)
    mis = renders.make_integrator("mis", {})
    guided = renders.make_integrator("guided_path", {"train_fraction": 0.75,
                                                     "combine_passes": False})
    v_mis, mean_mis = pixel_variance(sky, mis, 32, seeds=16)
    v_guided, mean_guided = pixel_variance(sky, guided, 128, seeds=16)
    assert guided.training[-1]["trained_leaves"] > 0
    assert guided.training[-1]["bsdf_share"] > 0.8, guided.training
    assert v_guided < 1.6 * v_mis, (v_guided, v_mis)
    assert abs(mean_guided / mean_mis - 1) < 0.05
    room = renders.load_scene(ROOM, res=16)
    # (every density kept: this room's guided pass at 16² × 64 spp measures
    # no gain, and the share is what is tested)
    guided = renders.make_integrator("guided_path", {"max_variance_ratio": 1e30})
    renders.render(room, guided, 64, seed=0)
    assert guided.training[-1]["bsdf_share"] < 0.6, guided.training


def test_the_training_images_join_the_result(llvm):
    """Each training pass renders an unbiased image too: combined in by
    inverse variance (the default; on 256 pixels nearly by spp), the result
    at 64 spp (16 of them training, as asked) keeps its mean
    and varies less than the last pass alone (0.75× if learning changed
    nothing; 0.55× on the Cornell box at 16², where what 16 spp learn is a
    poor density). With no training both are the same image."""
    scene = renders.load_scene(str(SCENES / "cornell_box.xml"), res=16)
    quarter = {"train_fraction": 0.25, "max_variance_ratio": 1e30}     # (every density kept)
    both = renders.make_integrator("guided_path", quarter)
    alone = renders.make_integrator("guided_path", {**quarter, "combine_passes": False})
    v_both, mean_both = pixel_variance(scene, both, 64, seeds=10)
    v_alone, mean_alone = pixel_variance(scene, alone, 64, seeds=10)
    assert sum(t["spp"] for t in both.training) == 16
    assert v_both < 0.9 * v_alone, (v_both, v_alone)
    assert abs(mean_both / mean_alone - 1) < 0.03, (mean_both, mean_alone)
    none = {"train_passes": 0}
    a = renders.render(scene, renders.make_integrator("guided_path", none), 8, seed=3).image
    b = renders.render(scene, renders.make_integrator(
        "guided_path", {**none, "combine_passes": False}), 8, seed=3).image
    assert np.array_equal(a, b)


def test_a_new_spp_compiles_nothing_that_one_like_it_compiled(llvm):
    """100 and 101 spp train in the same iterations (1, 2, 4, 8 and 16 spp)
    and render the rest undivided by a shift: the second launches only kernels the first
    had, none compiled or read from Dr.Jit's disk cache. With the passes'
    weights as literals it compiled the sum's; with the guide's arrays
    copied from numpy's memory as it lay, a copy's kernel for each
    alignment. A timed render that compiles is rendered again
    (run/renders.timed_render)."""
    scene = renders.load_scene(str(SCENES / "cornell_box.xml"), res=8)
    integrator = renders.make_integrator("guided_path", {"max_variance_ratio": 1e30})
    renders.render(scene, integrator, 100, seed=1)
    assert [t["spp"] for t in integrator.training] == [1, 2, 4, 8, 16]
    _, kernels = renders.launched(lambda: renders.render(scene, integrator, 101, seed=2))
    compiled = [k for k in kernels if not k["cache_hit"] or k["cache_disk"]]
    assert [t["spp"] for t in integrator.training] == [1, 2, 4, 8, 16]
    assert compiled == [], [(k["size"], k["hash"]) for k in compiled]


def test_mixture_share_runs_from_bsdf_fraction_to_one():
    share = guide().mixture_share
    assert share(0.5, 1.0) == 0.5 and share(0.5, 0.0) == 1.0 and share(0.2, 0.5) == 0.6


def test_scalar_variant_learns_and_renders(use_variant):
    use_variant("scalar_rgb")
    scene = renders.load_scene(ROOM, res=10)
    # (every density kept: what 10² × 2 spp learn is predicted to pay too little)
    guided = renders.make_integrator("guided_path", {"max_depth": 3, "max_variance_ratio": 1e30})
    out = renders.render(scene, guided, 32, seed=1)
    assert np.isfinite(out.image).all() and out.image.mean() > 0
    assert [t["spp"] for t in guided.training] == guide().budget_passes(32)
    assert guided.training[0]["records"] > 0 and guided.training[-1]["trained_leaves"] > 0
    assert 0 < guided.training[0]["variance_ratio"] < 10, guided.training


def test_where_nothing_arrives_indirectly_it_stops_learning(llvm):
    """Direct light only (max_depth 2): the emission a continuation hits is
    not learned (next-event estimation has it), so the first pass learns
    nothing and the rest of the samples render the image, as mis."""
    scene = renders.load_scene(str(SCENES / "cap_plane.xml"), res=16)
    guided = renders.make_integrator("guided_path", {"max_depth": 2})
    renders.render(scene, guided, 64, seed=0)
    assert len(guided.training) == 1 and guided.training[0]["records"] > 0
    assert guided.training[0]["trained_leaves"] == 0


def test_a_density_that_pays_too_little_is_dropped_and_the_rest_renders_as_mis(llvm):
    """sky_sphere (a smooth sky: light mostly direct) at 64² × 64 spp: what
    each iteration learns is predicted to leave over 0.8 of BSDF sampling's
    variance of the indirect light (0.98 here), drawn with no density; once
    JUDGED_FROM records are in (8 spp of training) training stops there and
    the rest renders as mis (whose mean it keeps); the same render with
    every density kept trains in all five iterations (1-16 spp).
    sunlit_room_hole (all light indirect, through a hole) predicts 0.58,
    then down to 0.07: it keeps guiding. The Cornell box at 128² × 40 spp
    predicts a gain (0.43-0.56 of the indirect light's variance), but the
    first iteration drawn with it of enough samples to measure (4 spp)
    measures more than 0.8 of the unguided iteration's relative variance
    per sample (2.4 here): the rest renders as mis, and what that
    iteration would teach is not learned. And the setting is checked."""
    sky = renders.load_scene(str(SCENES / "sky_sphere.xml"), res=64)
    dropped = renders.make_integrator("guided_path", {})
    kept = renders.make_integrator("guided_path", {"max_variance_ratio": 1e30})
    mean = renders.render(sky, dropped, 64, seed=2).image.mean()
    renders.render(sky, kept, 64, seed=2)
    judged = guide().JUDGED_FROM
    assert dropped.training[-1]["records"] >= judged > dropped.training[-2]["records"], \
        dropped.training
    assert all(t["variance_ratio"] > 0.8 for t in dropped.training), dropped.training
    assert len(kept.training) == 5 > len(dropped.training)
    mis = renders.render(sky, renders.make_integrator("mis", {}), 64, seed=2).image.mean()
    assert abs(mean / mis - 1) < 0.02, (mean, mis)
    hole = renders.load_scene(ROOM, res=64, gap="hole", sun=500)
    guided = renders.make_integrator("guided_path", {})
    renders.render(hole, guided, 64, seed=2)
    assert len(guided.training) == 5 and guided.training[-1]["variance_ratio"] < 0.6, \
        guided.training
    box = renders.load_scene(str(SCENES / "cornell_box.xml"), res=128)
    guided = renders.make_integrator("guided_path", {})
    mean = renders.render(box, guided, 40, seed=0).image.mean()
    assert len(guided.training) == 3 and guided.training[-1]["leaves"] is None
    assert guided.training[0]["variance_ratio"] <= 0.8 < guided.training[-1]["measured_ratio"]
    mis = renders.render(box, renders.make_integrator("mis", {}), 40, seed=0).image.mean()
    assert abs(mean / mis - 1) < 0.02, (mean, mis)
    with pytest.raises(Exception, match="max_variance_ratio"):
        mi.load_dict({"type": "guided_path", "max_variance_ratio": 0.0})


def test_a_pass_pixel_moments_are_its_image(llvm):
    """Records.pixel_moments reads lane // spp as a lane's pixel (Mitsuba's
    wavefront holds a pixel's samples side by side): under a box filter
    each pixel's mean path radiance is the training pass's image there."""
    g = guide()
    # (a film wider than tall: rows and columns cannot be swapped unseen)
    scene = tiny_scene(12, 8, sphere={"type": "sphere", "bsdf": {"type": "diffuse"}},
                       floor=disk({"type": "diffuse"}),
                       sky={"type": "constant",
                            "radiance": {"type": "rgb", "value": [0.2, 0.5, 1.0]}})
    integrator = renders.make_integrator("guided_path", {"train_passes": 1,
                                                        "train_fraction": 0.5})
    seen = {}
    launch, moments = integrator.launch, g.Records.pixel_moments

    def first_launch(*args):
        image = launch(*args)
        seen.setdefault("image", np.array(image)[..., :3].mean(axis=-1))
        return image

    def read(records):
        seen.setdefault("moments", moments(records))
        return seen["moments"]
    integrator.launch = first_launch
    g.Records.pixel_moments = read
    try:
        renders.render(scene, integrator, 8, seed=3)
    finally:
        g.Records.pixel_moments = moments
    (first, second, n), (first_b, _, n_b) = seen["moments"]
    assert n == n_b == 2 and first.shape == (96,)
    assert np.all(second * n >= first ** 2 * (1 - 1e-6))
    assert np.allclose((first + first_b).reshape(8, 12) / 4, seen["image"],
                       rtol=1e-4, atol=1e-6)


def test_measured_ratios_read_relative_variance_and_unseen_light(llvm):
    """guide.measured_ratios on samples of known spread: per pixel μ (0.1-2),
    the unguided pass's samples spread 0.8 μ at 1 spp, the guided pass's
    0.4 μ at 3 spp: a relative variance ratio of 0.25 (0.79 with each
    pixel weighed by its own samples' mean), means alike. Where the
    unguided pass saw a third of the light, the means' ratio says so."""
    g = guide()
    rng = np.random.default_rng(5)
    mu = rng.uniform(0.1, 2.0, 20000)

    def moments(spread, n, scale=1.0):
        x = mu[:, None] * scale * (1 + spread * rng.standard_normal((mu.size, n)))
        m = g.PixelMoments()
        m.add([(h.sum(axis=1), np.square(h).sum(axis=1), h.shape[1])
               for h in (x[:, 0::2], x[:, 1::2])])
        return m
    unguided = moments(0.8, 1)
    variance, means = g.measured_ratios(unguided, moments(0.4, 3))
    assert abs(variance / 0.25 - 1) < 0.1 and abs(means - 1) < 0.02, (variance, means)
    _, means = g.measured_ratios(moments(0.8, 1, scale=1 / 3), moments(0.4, 3))
    assert means > 2.5 > g.UNSEEN_ABOVE
    assert np.isnan(g.measured_ratios(g.PixelMoments(), moments(0.4, 3))[0])


def test_nested_in_moment_it_renders_as_mis(llvm):
    scene = renders.load_scene(ROOM, res=8)
    moment = mi.load_dict({"type": "moment", "nested": {"type": "guided_path"}})
    image = np.array(mi.render(scene, integrator=moment, spp=16, seed=0))
    assert np.isfinite(image).all() and image[..., :3].mean() > 0


# --------------------- The suite's verdict, right and wrong -------------------

TWIN = textwrap.dedent('''
    import mcillum
    import mitsuba as mi

    cls = type(mi.load_dict({"type": "guided_path"}))

    class LearnedPdfHigh(cls):
        """The learned density 25 % high in the weight and the MIS weights;
        its samples drawn as they should be."""
        plugin_name = "guided_path_pdf_high"

        def guide_density(self, si, base, wo_world):
            return 1.25 * super().guide_density(si, base, wo_world)

    mi.register_integrator("guided_path_pdf_high", lambda props: LearnedPdfHigh(props))
''')


@pytest.mark.slow
def test_the_suite_passes_it_and_fails_a_wrong_learned_pdf(llvm, tmp_path):
    """On the scene made for it (24², the user-scene ladder up to 256 spp,
    where every render learns), the twin with the learned pdf 25 % high in
    the weight fails, and guided_path passes every unbiasedness check. The
    twin first: a correct estimator left inconclusive ends the test as an
    xfail (mcillum.testing), and the twin's fail must still be read. Trained
    across the budget (issue 65), guided_path is inconclusive here on seed
    set 0: its image mean -1.2 % ± 1.1 % reaches past ε = 2 %, with no bias
    the fresh renders confirm (300 and 150 renders read z = 0.74 and 0.51)."""
    plugin = tmp_path / "twin.py"
    plugin.write_text(TWIN)
    wrong = compare(ROOM, "guided_path_pdf_high", plugins=[plugin], out_dir=tmp_path / "wrong",
                    cache_dir=tmp_path / "cache")
    with pytest.raises(AssertionError, match="fail"):
        assert_unbiased(wrong)
    right = compare(ROOM, "guided_path", out_dir=tmp_path / "right",
                    cache_dir=tmp_path / "cache")
    assert_unbiased(right)


# ----------------------------- The learning stage -----------------------------

def test_the_learning_stage_asks_for_the_passes_the_plugin_makes(llvm):
    """stages/learning.training: the image keeps its spp u and the plugin
    trains in exactly u, 2u, 4u, … before it; u is a quarter of the
    ladder's top rung."""
    from mcillum.validation.stages import learning
    for spp in (1, 4, 16, 512, 1024):
        for j in learning.PASSES:
            total, params = learning.training(spp, j)
            passes = guide().training_passes(total, params["train_fraction"],
                                             params["train_passes"])
            assert passes == [spp * 2 ** i for i in range(j)], (spp, j, passes)
            assert total - sum(passes) == spp
    assert [learning.image_spp(x) for x in ((16, 64), (4096,), (1, 2))] == [16, 1024, 1]


def test_train_passes_is_honoured_and_checked(llvm):
    scene = renders.load_scene(ROOM, res=8)
    guided = renders.make_integrator("guided_path", {"train_passes": 3, "train_fraction": 0.5,
                                                     "max_variance_ratio": 1e30})
    renders.render(scene, guided, 64, seed=0)
    assert [t["spp"] for t in guided.training] == guide().training_passes(64, 0.5, 3)
    assert len(guided.training) == 3
    for bad in (-1, 1.5, True):
        with pytest.raises(Exception, match="train_passes"):
            mi.load_dict({"type": "guided_path", "train_passes": bad})


def test_the_learning_stage_records_error_against_training(llvm, tmp_path):
    """A scene run with ``learning = true``: guided_path's relMSE at a
    quarter of the top rung's spp after 0–4 training passes of it and its
    doublings, in results.json (schema-valid) and
    the report; without the flag, no stage and no record."""
    import json

    import jsonschema

    from mcillum.validation import pipeline, results
    from mcillum.validation.plan import profiles

    def run(flag, out):
        plan = profiles.SceneRun(scene="sunlit_room", res=4, ladder=(16, 64), renders=4,
                                 learning=flag)
        profile = profiles.Profile(name="learning", runs=(plan,),
                                   estimators=("guided_path", "path"), reference_max_seconds=10.0)
        return pipeline.validate(profile, out_dir=str(out), cache_dir=str(tmp_path / "cache"),
                                 groups=("scenes",), speed_stage=False, progress=False)

    found = run(True, tmp_path / "on")
    learned = found.scenes[0].learning
    assert [x.name for x in learned] == ["guided_path"]
    points = learned[0].points
    assert [p.training_spp for p in points] == [0, 16, 48, 112, 240]
    assert learned[0].spp == 16 and learned[0].renders == 4
    assert all(np.isfinite(p.relmse) and p.relmse_low <= p.relmse <= p.relmse_high
               for p in points)
    data = json.loads((tmp_path / "on" / "results.json").read_text())
    jsonschema.validate(data, json.load(open(results.SCHEMA_FILE)))
    assert data["scenes"][0]["learning"][0]["points"][4]["training_spp"] == 240
    page = (tmp_path / "on" / "report" / "index.html").read_text()
    assert "Learning: error against training" in page
    assert run(False, tmp_path / "off").scenes[0].learning is None


def test_a_users_integrator_and_scene_can_ask_for_the_learning_stage(llvm):
    """A user's class declares ``learns`` (a fact it may declare); a
    profile's [user_scenes] ``learning = true`` reaches every scene given
    by path."""
    from mcillum.integrators.core import registry
    from mcillum.validation.plan import profiles, user_scenes
    from mcillum.validation.stages import learning

    class Mine:
        learns = True
        colour = "#123456"

    registry.learn("my_learner", Mine)
    try:
        assert learning.learners(["my_learner", "mis", "guided_path"]) == \
            ["my_learner", "guided_path"]
    finally:
        registry._learned.pop("my_learner", None)
    plan = profiles.UserScenes(res=8, ladder=(16, 64), renders=4, learning=True)
    profile = profiles.Profile(name="mine", runs=(), user_scenes=plan)
    run, _ = user_scenes.scene_run(profile, ROOM)
    assert run.learning and learning.planned_renders(["guided_path"], 4, run) == 20
