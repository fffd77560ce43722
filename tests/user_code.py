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
