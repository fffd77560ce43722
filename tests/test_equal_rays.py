"""The quadrature stage's equal-ray pair (validation/stages/quadrature.py):
the baseline's error at N·spp read off its ladder renders at spp and scaled
by 1/N where the scene's sampler is independent, rendered at N·spp where it
is not; the two readings agree."""

from __future__ import annotations

import math

import pytest

from mcillum.validation.plan import profiles
from mcillum.validation.stages import quadrature

SET = "fibonacci_hemisphere"
BASELINE = "cosine_hemisphere"


def _stage(tmp_path, scene: str, plan=None, res=8, ladder=(16,), renders=16):
    """The scene-comparison stages up to the quadrature stage on the lone
    sphere under 'sg' (or ``plan``, a user's scene): the context."""
    from mcillum.validation import pipeline
    from mcillum.validation.stages import common
    from mcillum.validation.stages.context import Context, Run

    profile = profiles.Profile(name="quick", runs=(), reference_max_seconds=20.0)
    plan = plan or profiles.SceneRun(scene=scene, res=res, ladder=ladder, renders=renders,
                                     max_depth=2, defines={"envmap": "sg"})
    ctx = Context(Run(profile, "llvm_ad_rgb", str(tmp_path / "cache"), str(tmp_path / "out")),
                  plan, plan.id, [SET, BASELINE, "path"], dict(plan.defines))
    common.load(ctx)
    common.choose_estimators(ctx)
    for stage in (pipeline.scene.render_ladder, common.build_reference,
                  pipeline.quadrature.measure):
        stage(ctx)
    return ctx


def _log_se(r) -> float:
    return math.log(r.ratio_high / r.ratio_low) / (2 * 1.96)


def test_the_baseline_read_at_the_ladder_agrees_with_one_rendered_at_n_spp(llvm, tmp_path,
                                                                         monkeypatch):
    """Lone sphere, 8², 16 renders at 16 spp, N = 64: cosine's net relMSE
    at 1 024 spp read as its ladder renders' over 64 agrees with 16 renders
    at 1 024 spp within their intervals (a reading that forgot the 1/N
    would be 64× off). Over seed sets 10-19 at 16² the two readings'
    ratio averaged 1.002 (sd 0.062;
    docs/measurements.md#2026-12-04-quadrature-stage-reads-baseline)."""
    ctx = _stage(tmp_path / "law", "lone_sphere")
    law = ctx.quadrature[SET].equal_rays
    assert law.baseline == BASELINE and law.baseline_spp == 64 * 16
    assert law.baseline_read_at == 16

    def rendered(ctx, against, rays, spp, k, block):
        return quadrature._renders(ctx, against, {}, rays, k, block)
    monkeypatch.setattr(quadrature, "_baseline", rendered)
    ctx = _stage(tmp_path / "rendered", "lone_sphere")
    direct = ctx.quadrature[SET].equal_rays
    assert direct.baseline_read_at == 64 * 16
    gap = abs(math.log(law.ratio / direct.ratio))
    assert gap < 2.5 * math.hypot(_log_se(law), _log_se(direct)), (law, direct)
    assert law.seconds > 0 and law.baseline_seconds > law.seconds / 64


def test_a_scene_with_a_stratified_sampler_renders_the_baseline_at_n_spp(llvm, tmp_path):
    """A user's copy of the lone sphere with a multijitter sampler: its
    samples are not independent, so 1/N does not hold and the baseline is
    rendered at N·spp."""
    from mcillum.validation.plan import scenes, user_scenes

    text = open(scenes.path("lone_sphere")).read()
    assert 'sampler type="independent"' in text
    path = tmp_path / "jittered.xml"
    path.write_text(text.replace('sampler type="independent"', 'sampler type="multijitter"'))
    profile = profiles.QUICK
    plan, _ = user_scenes.scene_run(profile, str(path), defines={"envmap": "sg"}, res=8,
                                    settings={"max_depth": 2})
    plan = profiles.SceneRun(**{**plan.__dict__, "ladder": (4,), "renders": 4,
                                "display": None})
    ctx = _stage(tmp_path, str(path), plan=plan)
    rays = ctx.quadrature[SET].equal_rays
    assert rays.baseline_read_at == rays.baseline_spp == 64 * 4


@pytest.mark.parametrize("names, timed", [([SET], 2), ([SET, "bayesian_hemisphere"], 3),
                                          ([SET, "bayesian_importance"], 4)])
def test_planned_renders_count_one_timing_per_baseline(llvm, names, timed):
    """The progress bar's count: TIMED renders per estimator and per
    distinct baseline, K per extra N of one biased by design."""
    from mcillum.integrators.core import registry

    biased = sum(not registry.facts(n).unbiased for n in names) * len(
        quadrature.BIAS_DIRECTIONS)
    assert quadrature.planned_renders(names, 8) == quadrature.TIMED * timed + 8 * biased
