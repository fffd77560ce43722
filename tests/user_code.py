"""A user's own code, as a file outside the repository holds it: a first
integrator (direct light by emitter sampling, no ``max_depth``) and its broken
twin. test_user_scenes.py and test_testing_api.py write it into a temporary
folder and import it through ``--plugin`` / ``plugins=``."""

#: A user's first integrator: direct light by emitter sampling, no max_depth.
#: ``my_direct_broken`` is its twin whose light samples are 5 % too dark.
MY_INTEGRATOR = '''
import mitsuba as mi


class MyDirect(mi.SamplingIntegrator):
    display_name = "my direct light"

    def __init__(self, props):
        super().__init__(props)
        self.weight = props.get("weight", 1.0)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        si = scene.ray_intersect(ray, active)
        L = si.emitter(scene, active).eval(si, active)
        hit = active & si.is_valid()
        ds, w = scene.sample_emitter_direction(si, sampler.next_2d(hit), True, hit)
        f = si.bsdf(ray).eval(mi.BSDFContext(), si, si.to_local(ds.d), hit)
        return L + self.weight * w * f, si.is_valid(), []


class MyDirectBroken(MyDirect):
    def __init__(self, props):
        super().__init__(props)
        self.weight = 0.95


mi.register_integrator("my_direct", lambda props: MyDirect(props))
mi.register_integrator("my_direct_broken", lambda props: MyDirectBroken(props))
'''

#: Mitsuba's path tracer rendering every image twice and keeping the first:
#: the same error as `path` at twice the cost, fixed cost included, so an
#: efficiency against `path` whose truth is known (test_validate.py).
TWICE_PATH = '''
import drjit as dr
import mitsuba as mi


class TwicePath(mi.SamplingIntegrator):
    def __init__(self, props):
        super().__init__(props)
        inner = {"type": "path"}
        for key in ("max_depth", "rr_depth", "hide_emitters"):
            if key in props:
                inner[key] = props[key]
        self.inner = mi.load_dict(inner)

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        kept = self.inner.render(scene, sensor, seed, spp, develop, evaluate)
        thrown = self.inner.render(scene, sensor, seed + 1, spp, develop, evaluate)
        dr.eval(kept, thrown)
        return kept

    def sample(self, scene, sampler, ray, medium=None, active=True):
        return self.inner.sample(scene, sampler, ray, medium, active)


mi.register_integrator("twice_path", lambda props: TwicePath(props))
'''

#: Mitsuba's path tracer with each sample weighted by W, Pareto of mean 1 and
#: shape 1.5: unbiased, but W has no finite variance, so rare samples carry
#: the error and a mean over renders misses them (test_validate.py).
SPIKY_PATH = '''
import drjit as dr
import mitsuba as mi


class SpikyPath(mi.SamplingIntegrator):
    def __init__(self, props):
        super().__init__(props)
        self.inner = mi.load_dict({"type": "path"})

    def sample(self, scene, sampler, ray, medium=None, active=True):
        spec, valid, aovs = self.inner.sample(scene, sampler, ray, medium, active)
        u = sampler.next_1d(active)
        a = 1.5                                 # P(W > w) = (x_m / w)^a, x_m = (a - 1)/a
        return spec * ((a - 1) / a) * dr.power(1 - u, -1 / a), valid, aovs


mi.register_integrator("spiky_path", lambda props: SpikyPath(props))
'''

#: Appended to :data:`MY_INTEGRATOR`: a user's quadrature, derived from
#: mcillum's bayesian_hemisphere with every direction's weight 5 % low (biased
#: by design, and by 5 % more); and their direct-light integrator, 5 % dark,
#: declaring itself biased by design although nothing measures it against N.
MY_QUADRATURE = '''

Bayes = type(mi.load_dict({"type": "bayesian_hemisphere"}))


class MyBayesLow(Bayes):
    def direction(self, j, drawn, si, bsdf, ctx, active):
        wo, f, a = super().direction(j, drawn, si, bsdf, ctx, active)
        return wo, f * 0.95, a


class MyDirectDeclaredBiased(MyDirectBroken):
    unbiased = False


mi.register_integrator("my_bayes_low", lambda props: MyBayesLow(props))
mi.register_integrator("my_direct_declared_biased",
                       lambda props: MyDirectDeclaredBiased(props))
'''

#: A user's direct-light integrator that samples the BSDF only (no emitter
#: samples): heavy-tailed under a small sun, which only a BSDF sample that
#: escapes towards it finds. ``my_bsdf_direct_low`` is its twin whose
#: weights are 5 % low: under a sun the tail can excuse its darker mean.
MY_BSDF_DIRECT = '''
import mitsuba as mi


class MyBsdfDirect(mi.SamplingIntegrator):
    display_name = "my BSDF-sampled direct light"
    weight = 1.0

    def sample(self, scene, sampler, ray, medium=None, active=True):
        si = scene.ray_intersect(ray, active)
        L = si.emitter(scene, active).eval(si, active)        # light seen directly
        hit = active & si.is_valid()
        bs, f = si.bsdf(ray).sample(mi.BSDFContext(), si, sampler.next_1d(hit),
                                    sampler.next_2d(hit), hit)
        hit &= bs.pdf > 0
        # (a miss returns the environment emitter: the sun is found only here)
        lit = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), hit)
        Le = lit.emitter(scene, hit).eval(lit, hit)
        return L + self.weight * f * Le, si.is_valid(), []


class MyBsdfDirectLow(MyBsdfDirect):
    weight = 0.95


mi.register_integrator("my_bsdf_direct", lambda props: MyBsdfDirect(props))
mi.register_integrator("my_bsdf_direct_low", lambda props: MyBsdfDirectLow(props))
'''
