"""mcillum: Monte Carlo estimators of the illumination integral as Mitsuba 3
plugins, and the suite that validates them against Mitsuba's path tracer.

This folder holds the package's own modules; ``pyproject.toml`` maps the
repository's top-level folders into it:

* :mod:`mcillum.integrators` — the plugins, one estimator per file, and the
  registry of their facts;
* :mod:`mcillum.envmaps` — environment maps: real probes, procedural maps with
  closed forms, and the loading policy every map passes through;
* :mod:`mcillum.validation` — scene → renders → reference → statistics →
  checks → results → report, and the ``mcillum`` command;
* :mod:`mcillum.files` — atomic writes, EXR files and the cache directory,
  shared by envmaps and validation;
* ``mcillum.scenes`` — the Mitsuba XML scenes of ``scenes/`` (data only).

``import mcillum`` points Dr.Jit at the bundled libLLVM (so import it before
``drjit`` or ``mitsuba``) and registers the plugins for the current Mitsuba
variant, and again after every ``mi.set_variant``.
"""

from . import integrators  # noqa: F401  (must come first: LLVM set-up, plugin registration)
from .integrators import UnreachableContentError, register  # noqa: F401
