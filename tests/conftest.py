"""Shared fixtures: variants, scene paths, the estimators under test (read from
the registry) and batches of independent renders. The broken twins live in
twins.py."""

from __future__ import annotations

import gc
import ipaddress
import signal
import socket
from pathlib import Path

import numpy as np
import pytest

import mcillum  # noqa: F401  (LLVM set-up before drjit; registers the plugins)
import mitsuba as mi

from mcillum.integrators.core import registry
from mcillum.validation.run import renders

from twins import has_pdf_pair, plugin_class

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"

#: Variants every rendering test runs in (scalar with tiny images).
VARIANTS = ["scalar_rgb", "llvm_ad_rgb"]

renders.set_variant("llvm_ad_rgb")      # the registry fills when a variant is set

# A test run started in the background by a non-interactive shell (`nohup make
# test &`) inherits SIGINT ignored, and so would every process it starts: the
# tests that send SIGINT to a render or a CLI run would see it vanish. A
# handler (unlike SIG_IGN) resets to the default in a child, whose Python then
# raises KeyboardInterrupt as it does under a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def estimators() -> list[str]:
    """Every registered mcillum estimator of paths (registry order): those
    that define every max_depth. The estimators of N directions per point
    (direct light only, one biased by design) have their own tests:
    test_direction_sets.py, and :data:`POINT_SETS`."""
    return [n for n in registry.names() if registry.facts(n).depths is None]


def point_sets() -> list[str]:
    """The registered estimators of N directions per shading point."""
    return [n for n in registry.names() if registry.facts(n).depths is not None]


def hemisphere_estimators() -> list[str]:
    """Estimators defined by a pure direction pair ``sample_local`` /
    ``pdf_local`` on the hemisphere (they get a wrong-pdf twin)."""
    return [n for n in estimators() if has_pdf_pair(plugin_class(n))]


#: Fixed at collection time (parametrize needs lists).
ALL_ESTIMATORS = estimators()
HEMISPHERE = hemisphere_estimators()
POINT_SETS = point_sets()


class OffMachineError(RuntimeError):
    """A test tried to reach an address other than this machine's loopback."""


def _check_loopback(address) -> None:
    if not isinstance(address, tuple):                 # AF_UNIX paths stay local
        return
    host = str(address[0]).split("%")[0]
    if host == "localhost":
        return
    try:
        if ipaddress.ip_address(host).is_loopback:
            return
    except ValueError:                                 # a name: resolving it is a packet
        pass
    raise OffMachineError(f"a test tried to reach {host}: tests may only address the "
                          "loopback (use 127.0.0.1 and a closed port for a refused request)")


@pytest.fixture(autouse=True, scope="session")
def loopback_only():
    """No test sends a packet off this machine: this process may look up,
    connect or send only to loopback addresses (browsers started by tests run
    with background networking off and are given loopback URLs)."""
    real = socket.socket.connect, socket.socket.connect_ex, socket.socket.sendto
    real_getaddrinfo = socket.getaddrinfo

    def getaddrinfo(host, *args, **kwargs):             # (a name lookup is a packet)
        if host is not None:
            _check_loopback((host.decode() if isinstance(host, bytes) else host, 0))
        return real_getaddrinfo(host, *args, **kwargs)

    def connect(self, address):
        _check_loopback(address)
        return real[0](self, address)

    def connect_ex(self, address):
        _check_loopback(address)
        return real[1](self, address)

    def sendto(self, data, *args):
        _check_loopback(args[-1])
        return real[2](self, data, *args)

    socket.socket.connect, socket.socket.connect_ex, socket.socket.sendto = (
        connect, connect_ex, sendto)
    socket.getaddrinfo = getaddrinfo
    yield
    socket.socket.connect, socket.socket.connect_ex, socket.socket.sendto = real
    socket.getaddrinfo = real_getaddrinfo


@pytest.fixture(autouse=True, scope="module")
def release_scenes(request):
    """After each test module, the scenes its caches hold are released.

    Every live scene joins the registry Dr.Jit's virtual calls dispatch
    over, so each render in the process slows with every scene kept alive
    (docs/measurements.md#2026-12-02-default-test-group-live); the modules'
    ``functools.lru_cache`` helpers keep theirs for the rest of the run unless
    cleared here."""
    yield
    for value in list(vars(request.module).values()):
        clear = getattr(value, "cache_clear", None)
        if callable(clear) and hasattr(value, "cache_info"):
            clear()
    gc.collect()


@pytest.fixture(params=VARIANTS)
def variant(request):
    """Switch Mitsuba to each test variant in turn."""
    return renders.set_variant(request.param)


@pytest.fixture
def use_variant():
    """``renders.set_variant`` for a test parametrised by variant name; llvm
    is restored afterwards."""
    yield renders.set_variant
    renders.set_variant("llvm_ad_rgb")


@pytest.fixture
def llvm():
    return renders.set_variant("llvm_ad_rgb")


def small(variant: str, scalar: int, vectorized: int) -> int:
    """Pick a size: scalar variants run Python per sample, so keep them tiny."""
    return scalar if variant.startswith("scalar") else vectorized


def tiny_scene(width: int = 2, height: int = 2, **items):
    """A camera (2x2 by default, box filter) looking down at whatever
    ``items`` add."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(
                       origin=[0, 3, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": width, "height": height,
                            "rfilter": {"type": "box"}}},
        **items,
    })


def disk(bsdf):
    return {"type": "disk", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90),
            "bsdf": bsdf}


def render(scene, name, **params):
    """One 2-spp render of ``scene`` with integrator ``name``."""
    return renders.render(scene, renders.make_integrator(name, params), spp=2)


def batch(scene, integrator, spp: int, k: int, first_seed: int = 0) -> np.ndarray:
    """K independent renders (seeds first_seed … first_seed+k-1), (K, H, W, C)."""
    return np.stack([renders.render(scene, integrator, spp, seed).image
                     for seed in range(first_seed, first_seed + k)])


def disagreements(first: dict, second: dict, first_ranking, second_ranking,
                  tolerance: float = 0.15) -> list[str]:
    """What two runs of the speed stage disagree on: efficiency ratios against
    `path` ({name: Ratio}) more than ``tolerance`` apart where both runs call
    the figure unbiased (results.KINDS) and state intervals narrower than
    ± ``tolerance``, and pairs that one run separates one way and the other
    the other way (costs.separated)."""
    from mcillum.validation.stats import costs

    def sharp(r) -> bool:
        return getattr(r, "kind", "unbiased") == "unbiased" and \
            r.ci.high / r.ratio - 1 <= tolerance and 1 - r.ci.low / r.ratio <= tolerance

    out = [f"{n}: efficiency ÷ path {r.ratio:.3g} then {second[n].ratio:.3g}"
           for n, r in first.items()
           if n in second and sharp(r) and sharp(second[n])
           and abs(second[n].ratio / r.ratio - 1) > tolerance]
    out += [f"{a} beat {b}, then {b} beat {a}"
            for a, b in costs.separated(first_ranking)
            if (b, a) in costs.separated(second_ranking)]
    return out
