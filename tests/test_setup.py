"""The LLVM set-up: a plain pip install gives working llvm_* variants.

Each case runs in a fresh interpreter, since Dr.Jit picks its libLLVM once per
process at `import drjit`.
"""

import os
import subprocess
import sys
import textwrap

import pytest

from mcillum.integrators import _llvm


def run_python(code: str, **env_overrides) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    env.update(env_overrides)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=300)


needs_bundled = pytest.mark.skipif(_llvm.bundled_libllvm() is None,
                                   reason="karellen-llvm-core is not installed")


@needs_bundled
def test_import_mcillum_gives_working_llvm():
    result = run_python("""
        import os, mcillum
        import drjit as dr, mitsuba as mi
        from mcillum.integrators import _llvm
        assert os.environ["DRJIT_LIBLLVM_PATH"] == _llvm.bundled_libllvm()
        assert dr.detail.llvm_version()[0] >= 17, dr.detail.llvm_version()
        mi.set_variant("llvm_ad_rgb")
        x = mi.Float([1.0, 3.0])
        print(dr.minimum(x, 2.0))   # the operation that aborts with LLVM 15/16
        """)
    assert result.returncode == 0, result.stderr
    assert "[1, 2]" in result.stdout


@needs_bundled
def test_user_setting_is_respected():
    path = _llvm.bundled_libllvm()
    result = run_python("""
        import os, mcillum
        print(os.environ["DRJIT_LIBLLVM_PATH"])
        """, DRJIT_LIBLLVM_PATH=path + "")
    assert result.returncode == 0 and result.stdout.strip() == path


IMPORT_DRJIT_FIRST = """
    import drjit                      # picks its LLVM before we can help
    import mcillum, mitsuba as mi
    try:
        mi.set_variant("llvm_ad_rgb")
        x = mi.Float([1.0, 3.0])
        print("RESULT:", drjit.minimum(x, 2.0))
    except Exception as e:
        print("ERROR:", e)
    """

OLD_LLVM = [p for p in ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1",
                        "/usr/lib/x86_64-linux-gnu/libLLVM-16.so.1") if os.path.exists(p)]


@pytest.mark.skipif(not OLD_LLVM, reason="no Debian libLLVM 15/16 on this machine")
def test_drjit_imported_first_with_crashing_llvm_fails_clearly():
    """LLVM 15 loads, then aborts the process on the first min/max: we must
    stop before that with a message that says what to do."""
    result = run_python(IMPORT_DRJIT_FIRST, DRJIT_LIBLLVM_PATH=OLD_LLVM[0])
    assert "ERROR:" in result.stdout, result.stdout + result.stderr
    message = result.stdout
    assert "Dr.Jit loaded LLVM 1" in message and "crashes" in message
    assert "import mcillum first" in message
    assert f"DRJIT_LIBLLVM_PATH={_llvm.bundled_libllvm()}" in message


def test_drjit_imported_first_without_llvm_fails_clearly():
    result = run_python(IMPORT_DRJIT_FIRST, DRJIT_LIBLLVM_PATH="/nonexistent/libLLVM.so")
    assert result.returncode == 0 and "ERROR:" in result.stdout, result.stderr
    # Mitsuba refuses the variant itself here; its message names the variable.
    assert "DRJIT_LIBLLVM_PATH" in result.stdout


def test_scalar_needs_no_llvm():
    result = run_python("""
        import drjit
        import mcillum, mitsuba as mi
        mi.set_variant("scalar_rgb")
        print(mi.load_dict({"type": "cosine_hemisphere"}).to_string())
        """, DRJIT_LIBLLVM_PATH="/nonexistent/libLLVM.so")
    assert result.returncode == 0, result.stderr
    assert "CosineHemisphereIntegrator" in result.stdout
