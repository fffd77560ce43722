"""A user's own integrators: modules or files that register Mitsuba plugins.

``mcillum validate --plugin my_integrator.py`` (also ``render`` and
``bench``, and ``plugins = [...]`` in a profile file) imports the user's
code before anything is rendered, so that the integrators it registers
(``mi.register_integrator("my_direct", ...)``) can be named like Mitsuba's
own. A file is imported under its stem as module name; a dotted name is
imported from ``sys.path``.

A :class:`Plugin` records what was imported, with its bytes' hash and the
bytes themselves, so that a Ray worker (validation/run/ray_executor.py)
imports the same code: from the same path where its file there has the same
hash, else from a copy written into its node's cache.

Registration binds a plugin class to the Mitsuba variant set at import time,
so :func:`load` runs after the variant is chosen, and imports again after a
variant switch.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import os
import sys
from dataclasses import dataclass, field

from . import files
from .errors import UsageError, message, root_cause


@dataclass(frozen=True)
class Plugin:
    """One imported module of a user's integrators."""

    spec: str                      # as given: a file or a dotted module name
    module: str                    # the name it is imported under
    path: str                      # its file (absolute)
    sha256: str                    # of the file's bytes
    source: bytes = field(default=b"", repr=False, compare=False)


#: path → (sha256, variant) of each file this process imported.
_imported: dict[str, tuple[str, str]] = {}


def is_file(spec: str) -> bool:
    """Does ``spec`` name a Python file rather than a dotted module?"""
    return files.names_a_file(spec, ".py")


def load(spec: str, variant: str | None = None) -> Plugin:
    """Import ``spec`` (a file or a module name) and return what was
    imported. Raises :class:`~mcillum.errors.UsageError` naming the file and
    the exception's last line when it cannot be found or imported."""
    if is_file(spec):
        path = os.path.abspath(spec)
        if not os.path.isfile(path):
            raise UsageError(f"--plugin {spec}: no such file")
        module = os.path.splitext(os.path.basename(path))[0]
    else:
        try:
            found = importlib.util.find_spec(spec)
        except (ImportError, ValueError) as err:
            found, why = None, message(err)
        else:
            why = "not found on sys.path"
        if found is None or not found.origin or not os.path.isfile(found.origin):
            raise UsageError(f"--plugin {spec}: cannot import module '{spec}': {why} "
                             "(give a file's path, or install the module)")
        path, module = os.path.abspath(found.origin), spec
    with open(path, "rb") as f:
        source = f.read()
    plugin = Plugin(spec, module, path, hashlib.sha256(source).hexdigest(), source)
    _import(plugin, path, variant)
    return plugin


def ensure(plugin: Plugin, variant: str | None = None) -> str:
    """Import ``plugin`` in this process (a Ray worker): from its own path
    where the file there has the same bytes, else from a copy of the
    driver's bytes in this node's cache. Returns the file imported."""
    path = plugin.path
    if not _same(path, plugin.sha256):
        path = os.path.join(files.cache_dir("plugins", plugin.sha256[:16]),
                            os.path.basename(plugin.path))
        if not _same(path, plugin.sha256):
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with files.atomic_path(path) as tmp:
                with open(tmp, "wb") as f:
                    f.write(plugin.source)
    _import(plugin, path, variant)
    return path


def sha256_of(path: str) -> str | None:
    """The sha256 of the file at ``path``; None where it cannot be read."""
    try:
        with open(path, "rb") as f:
            return hashlib.sha256(f.read()).hexdigest()
    except OSError:
        return None


def _same(path: str, sha256: str) -> bool:
    return sha256_of(path) == sha256


def _import(plugin: Plugin, path: str, variant: str | None) -> None:
    """Execute the plugin's file as module ``plugin.module`` unless this
    process already did for these bytes and this variant."""
    if _imported.get(plugin.path) == (plugin.sha256, variant):
        return
    folder = os.path.dirname(path)
    added = folder not in sys.path
    if added:                       # (its own imports of files beside it)
        sys.path.insert(0, folder)
    try:
        spec = importlib.util.spec_from_file_location(plugin.module, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[plugin.module] = module    # (pickling its classes finds them)
        spec.loader.exec_module(module)
    except BaseException as err:
        sys.modules.pop(plugin.module, None)
        if isinstance(err, KeyboardInterrupt):
            raise
        last = (message(err) or "").strip().splitlines() or [""]
        raise UsageError(f"--plugin {plugin.spec}: importing {plugin.path} failed: "
                         f"{type(root_cause(err)).__name__}: {last[-1]}") from None
    finally:
        if added:
            sys.path.remove(folder)
    _imported[plugin.path] = (plugin.sha256, variant)
