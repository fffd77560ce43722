"""Give Dr.Jit a working LLVM before it is first imported.

Dr.Jit 1.5 loads libLLVM when ``drjit`` is imported. It looks, in order, at a
libLLVM already loaded in the process, at ``$DRJIT_LIBLLVM_PATH`` (read once, at
import), at ``libLLVM.so`` on the loader path, then at the newest
``/usr/lib/x86_64-linux-gnu/libLLVM*.so.*``. On Debian bookworm that last one is
LLVM 15, which loads and then aborts the process on the first float min/max
("LLVM ERROR: Cannot select ... fminimum"); LLVM 14 is refused as too old.

The pinned wheel ``karellen-llvm-core==19.1.7`` ships a self-contained
libLLVM 19. :func:`configure` points ``DRJIT_LIBLLVM_PATH`` at it unless the user
set that variable, and :func:`check` refuses to go on when Dr.Jit was imported
earlier with an LLVM that would crash.

This module must not import drjit or mitsuba at module level.
"""

from __future__ import annotations

import os
import sys

#: Oldest LLVM major version that Dr.Jit 1.5 runs without crashing here.
MIN_LLVM_MAJOR = 17

_ENV = "DRJIT_LIBLLVM_PATH"


def bundled_libllvm() -> str | None:
    """Path of the libLLVM shipped by ``karellen-llvm-core``, or None."""
    try:
        from importlib import metadata

        files = metadata.files("karellen-llvm-core") or []
    except Exception:  # package absent or metadata unreadable
        return None
    candidates = []
    for f in files:
        name = f.name
        if name.startswith("libLLVM") and ".so" in name:
            path = os.path.realpath(str(f.locate()))
            if os.path.isfile(path):
                candidates.append(path)
    # All entries are symlinks to one file (libLLVM.so.19.1); pick any.
    return sorted(set(candidates))[0] if candidates else None


def configure() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` to the bundled libLLVM unless already set.

    Returns the path Dr.Jit will be told to use (None if neither the user nor
    the bundled wheel provides one). Has no effect once drjit is imported.
    """
    if os.environ.get(_ENV):
        return os.environ[_ENV]
    if "drjit" in sys.modules:
        return None
    path = bundled_libllvm()
    if path is not None:
        os.environ[_ENV] = path
    return path


class LLVMUnusableError(RuntimeError):
    """Dr.Jit was initialised with an LLVM that cannot run our kernels."""


def check(variant: str | None) -> None:
    """Raise :class:`LLVMUnusableError` if an ``llvm_*`` variant would crash.

    Only LLVM variants need libLLVM; scalar and CUDA variants pass untouched.
    """
    if not variant or not variant.startswith("llvm_"):
        return
    import drjit as dr

    major = dr.detail.llvm_version()[0]
    if major >= MIN_LLVM_MAJOR:
        return
    bundled = bundled_libllvm()
    how = (
        f"export {_ENV}={bundled} before starting Python"
        if bundled
        else "pip install 'karellen-llvm-core==19.1.7' (or install libLLVM >= 17) "
        f"and set {_ENV} to its libLLVM.so"
    )
    if major < 0:
        what = "Dr.Jit could not load any libLLVM"
        if os.environ.get(_ENV):
            what += f" ({_ENV}={os.environ[_ENV]} did not load)"
    else:
        what = (
            f"Dr.Jit loaded LLVM {major}, which crashes Dr.Jit 1.5 "
            f"(LLVM >= {MIN_LLVM_MAJOR} is needed)"
        )
    raise LLVMUnusableError(
        f"{what}, so variant '{variant}' cannot render. This happens when drjit "
        f"or mitsuba is imported before `import mcillum`. Fix: import "
        f"mcillum first, or {how}; or use variant 'scalar_rgb'."
    )
