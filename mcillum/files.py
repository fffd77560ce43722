"""Files mcillum writes: atomically, as EXR with metadata, and where caches live.

Every file goes to a temporary name beside its target and is renamed into
place, so a reader never sees a partial file. Temporary names say who wrote
them, ``.partial-mcillum-<host>-<pid>-<random><suffix>``: a process killed by
SIGKILL cannot remove its own, so :func:`remove_stale_partials` lets the next
run on the same host delete those whose process is gone.

Images are float32 OpenEXR. Metadata is stored as header attributes named
``mcillum.<key>``; extra channel groups (layers) as ``<layer>.RGB``.

Caches (generated environment maps, references) live under :func:`cache_dir`:
``$MCILLUM_CACHE`` if set, else ``~/.cache/mcillum``.

Nothing here imports Mitsuba or Dr.Jit.
"""

from __future__ import annotations

import hashlib
import inspect
import os
import socket
import tempfile
from contextlib import contextmanager
from functools import lru_cache
from importlib import metadata

import numpy as np

from .errors import UsageError

#: Prefix of every temporary file mcillum writes.
PARTIAL = ".partial-mcillum-"
#: Prefix of the custom EXR header attributes mcillum writes.
META_PREFIX = "mcillum."
#: EXR channel group of an image with this many channels.
_CHANNELS = {1: "Y", 3: "RGB", 4: "RGBA"}


def names_a_file(text: str, suffix: str) -> bool:
    """Does ``text``, given where a name or a file may stand (a scene, a
    plugin, a profile), name a file: it ends in ``suffix`` or holds a
    folder?"""
    return text.endswith(suffix) or os.sep in text or "/" in text


def cache_dir(*parts: str) -> str:
    """``$MCILLUM_CACHE`` (default ``~/.cache/mcillum``), joined with ``parts``."""
    root = os.environ.get("MCILLUM_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "mcillum")
    return os.path.join(root, *parts)


@lru_cache(maxsize=None)
def code_hash(*code) -> str:
    """sha256 of the source of ``code`` (functions or modules) and of the
    modules they live in, and of the installed mcillum and Mitsuba versions:
    the part of a cache key that says which code filled the cache (an edit or
    an upgrade makes a new key). Computed once per process."""
    h = hashlib.sha256()
    for dist in ("mcillum", "mitsuba"):
        try:
            h.update(f"{dist} {metadata.version(dist)}\n".encode())
        except metadata.PackageNotFoundError:   # a checkout that is not installed
            h.update(f"{dist} ?\n".encode())
    parts = [p for f in code for p in (f, inspect.getmodule(f))]
    for part in dict.fromkeys(parts):             # each module once
        try:
            h.update(inspect.getsource(part).encode())
        except (OSError, TypeError):              # installed without sources: bytecode
            compiled = getattr(part, "__code__", None)
            if compiled is not None:
                h.update(compiled.co_code + repr(compiled.co_consts).encode())
            else:
                with open(part.__file__, "rb") as f:
                    h.update(f.read())
    return h.hexdigest()


# ------------------------------ Atomic writes ---------------------------------

def _owner_tag() -> str:
    host = "".join(c if c.isalnum() else "_" for c in socket.gethostname())[:32]
    return f"{host}-{os.getpid()}-"


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it there on success.

    On any exception, including KeyboardInterrupt, the temporary file is
    removed and ``path`` is left as it was.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path)) or "."
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"output directory does not exist: {directory}")
    suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix=PARTIAL + _owner_tag(), suffix=suffix, dir=directory)
    os.close(fd)
    try:
        yield tmp
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp creates 0600
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:     # exists, owned by someone else
        return True
    return True


def remove_stale_partials(directory: str | os.PathLike, recursive: bool = False) -> list[str]:
    """Delete the temporary files in ``directory`` left by mcillum processes of
    this host that no longer run (killed mid-write); return their paths."""
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        return []
    host = _owner_tag().split("-")[0]
    removed = []
    walk = os.walk(directory) if recursive else [(directory, [], os.listdir(directory))]
    for root, _, names in walk:
        for name in names:
            if not name.startswith(PARTIAL):
                continue
            fields = name[len(PARTIAL):].split("-")
            if len(fields) < 3 or fields[0] != host or not fields[1].isdigit():
                continue
            if _alive(int(fields[1])):
                continue
            try:
                os.unlink(os.path.join(root, name))
                removed.append(os.path.join(root, name))
            except FileNotFoundError:
                pass
    return removed


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)


def write_arrays(path: str | os.PathLike, arrays: dict) -> None:
    """Write ``arrays`` (name → array) to ``path`` atomically as an .npz,
    uncompressed: zlib shrank float32 renders by a tenth at 34-44 MB/s,
    seconds of a full validation run for files kept only to resume it."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


# --------------------------------- EXR files ----------------------------------

def _group(image: np.ndarray, what: str) -> tuple[str, np.ndarray]:
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[2] not in _CHANNELS:
        raise ValueError(f"cannot store {what} of shape {image.shape} as EXR "
                         "(need (H, W, C) with C in 1, 3, 4)")
    group = _CHANNELS[image.shape[2]]
    if image.shape[2] == 1:
        # One channel goes to OpenEXR as (H, W): given (H, W, 1), OpenEXR 3.5
        # writes three channels <name>.R/G/B, read past the array's end.
        image = image[..., 0]
    return group, np.ascontiguousarray(image)


def write_exr(path: str | os.PathLike, image: np.ndarray, metadata: dict | None = None,
              layers: dict[str, np.ndarray] | None = None) -> str:
    """Write an (H, W, C) image, C in {1, 3, 4}, as float32 EXR, atomically.

    ``metadata`` values (str, int or float; others are stored as str) become
    header attributes ``mcillum.<key>``; ``layers`` are extra images of the
    same size stored as channel groups ``<name>.RGB`` (``.Y``, ``.RGBA``).
    Returns ``path``.
    """
    import OpenEXR

    group, pixels = _group(image, "an image")
    channels = {group: pixels}
    for name, layer in (layers or {}).items():
        g, p = _group(layer, f"layer '{name}'")
        if p.shape[:2] != pixels.shape[:2]:
            raise ValueError(f"layer '{name}' is {p.shape[:2]}, the image {pixels.shape[:2]}")
        channels[f"{name}.{g}"] = p
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (metadata or {}).items():
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            value = str(value)
        header[META_PREFIX + key] = value
    with atomic_path(path) as tmp:
        OpenEXR.File(header, channels).write(tmp)
    return os.fspath(path)


def read_exr(path: str | os.PathLike, layer: str = "") -> tuple[np.ndarray, dict]:
    """(H, W, C) float32 pixels of one channel group and the ``mcillum.*``
    metadata of an EXR written by :func:`write_exr` (``layer`` "" is the image)."""
    import OpenEXR

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such EXR file: {path}")
    f = OpenEXR.File(path)
    channels = f.channels()
    prefix = f"{layer}." if layer else ""
    for name in ("RGBA", "RGB", "Y"):
        if prefix + name in channels:
            pixels = np.asarray(channels[prefix + name].pixels, dtype=np.float32)
            break
    else:
        raise ValueError(f"{path}: no {prefix}RGB, {prefix}RGBA or {prefix}Y channels "
                         f"(has {sorted(channels)})")
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    meta = {k[len(META_PREFIX):]: v for k, v in f.header().items()
            if k.startswith(META_PREFIX)}
    return pixels, meta


# ------------------------------ Output paths ----------------------------------

class OutputPathError(UsageError, ValueError):
    """An output path that cannot be written (said before any work is done)."""


def check_writable_dir(directory: str | os.PathLike, what: str | None = None) -> None:
    """Raise :class:`OutputPathError` unless a file can be created in
    ``directory`` (tried, not guessed from permission bits, which root ignores)."""
    directory = os.fspath(directory)
    try:
        fd, probe = tempfile.mkstemp(prefix=PARTIAL + _owner_tag() + "probe-", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise OutputPathError(f"cannot write {what or directory}: no file can be created in "
                              f"{directory} ({err.strerror}); choose a writable location"
                              ) from None


def check_output(path: str | os.PathLike, what: str = "output") -> None:
    """Raise :class:`OutputPathError` for an output file path that cannot be
    written: a directory, a missing or non-directory parent, or a parent where
    no file can be created."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise OutputPathError(f"{what} {path} is a directory: give a file path")
    directory = os.path.dirname(os.path.abspath(path))
    if os.path.exists(directory) and not os.path.isdir(directory):
        raise OutputPathError(f"cannot write {what} {path}: {directory} is a file, not a "
                              "directory")
    if not os.path.isdir(directory):
        raise OutputPathError(f"output directory does not exist: {directory} (create it first)")
    check_writable_dir(directory, f"{what} {path}")


def make_dir(directory: str | os.PathLike, what: str, remedy: str = "") -> str:
    """Create ``directory`` (and parents) and check that it is writable; raise
    :class:`OutputPathError` naming ``what`` otherwise."""
    directory = os.fspath(directory)
    if os.path.exists(directory) and not os.path.isdir(directory):
        raise OutputPathError(f"{what} {directory} is a file, not a directory: give a "
                              "directory")
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as err:
        raise OutputPathError(f"cannot create {what} {directory}: {err.strerror}"
                              + (f" ({remedy})" if remedy else "")) from None
    check_writable_dir(directory, what)
    return directory
