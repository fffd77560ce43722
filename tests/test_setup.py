"""Installation: a plain pip install gives working llvm_* variants (each case in
a fresh interpreter, since Dr.Jit picks its libLLVM once per process at
`import drjit`), and installs one import package, `mcillum`.
"""

import os
import shutil
import subprocess
import sys
import textwrap
from importlib import metadata

import pytest

from mcillum.integrators import _llvm
from mcillum.integrators.core import registry

from conftest import ROOT


def run_python(code: str, **env_overrides) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    env.update(env_overrides)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=300)


#: karellen-llvm-core, the bundled libLLVM, is a dependency on Linux only
#: (pyproject.toml: ``sys_platform == 'linux'``); elsewhere it has no wheel.
linux = pytest.mark.skipif(sys.platform != "linux",
                           reason="karellen-llvm-core is a dependency on Linux only")


def bundled() -> str:
    """The bundled libLLVM; on Linux its absence is an installation error."""
    path = _llvm.bundled_libllvm()
    assert path is not None, (
        "karellen-llvm-core, a dependency of mcillum on Linux, is not installed (or has "
        "no libLLVM.so.*), so the llvm_* variants get whatever libLLVM the system has "
        "(Debian's 15/16 crash Dr.Jit): pip install 'karellen-llvm-core==19.1.7', or "
        "reinstall mcillum with its dependencies (pip install -e '.[test]')")
    return path


@linux
def test_bundled_libllvm_is_installed():
    assert os.path.isfile(bundled())


@linux
def test_import_mcillum_gives_working_llvm():
    result = run_python(f"""
        import os, mcillum
        import drjit as dr, mitsuba as mi
        assert os.environ["DRJIT_LIBLLVM_PATH"] == {bundled()!r}
        assert dr.detail.llvm_version()[0] >= 17, dr.detail.llvm_version()
        mi.set_variant("llvm_ad_rgb")
        x = mi.Float([1.0, 3.0])
        print(dr.minimum(x, 2.0))   # the operation that aborts with LLVM 15/16
        """)
    assert result.returncode == 0, result.stderr
    assert "[1, 2]" in result.stdout


def users_libllvm(tmp_path) -> str:
    """A working libLLVM at a path of the user's own, not the bundled one: a
    hard link to the bundled file (or a copy across file systems), so that
    /proc/self/maps names this path once it is loaded. Its folder holds the
    bundled file's sibling folders (symlinks), where the wheel's RUNPATH
    ($ORIGIN/../lib/x86_64-unknown-linux-gnu) finds libc++."""
    source = bundled()
    lib = tmp_path / "lib"
    lib.mkdir()
    mine = lib / "libLLVM.so"
    try:
        os.link(source, mine)
    except OSError:
        shutil.copy(source, mine)
    for entry in os.scandir(os.path.dirname(source)):
        if entry.is_dir():
            (lib / entry.name).symlink_to(entry.path)
    return str(mine)


@linux
def test_user_setting_is_respected(tmp_path):
    """mcillum leaves a DRJIT_LIBLLVM_PATH the user set as it is (here another
    path than the bundled one), and Dr.Jit loads that file."""
    mine = users_libllvm(tmp_path)
    assert mine != bundled()
    result = run_python("""
        import os, mcillum
        print(os.environ["DRJIT_LIBLLVM_PATH"])
        import drjit as dr
        print(dr.detail.llvm_version()[0])
        print(sorted({line.split()[-1] for line in open("/proc/self/maps")
                      if "libLLVM" in line}))
        """, DRJIT_LIBLLVM_PATH=mine)
    assert result.returncode == 0, result.stderr
    setting, major, loaded = result.stdout.strip().splitlines()[-3:]
    assert setting == mine, f"mcillum replaced the user's {mine} with {setting}"
    assert int(major) >= _llvm.MIN_LLVM_MAJOR and loaded == str([mine]), result.stdout


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
    assert f"DRJIT_LIBLLVM_PATH={bundled()}" in message


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


# --------------------------------- Packaging ------------------------------------

def _site_packages(python: str) -> str:
    return subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()"
                           "['purelib'])"], capture_output=True, text=True,
                          check=True).stdout.strip()


def test_install_adds_one_package_and_its_scenes(tmp_path):
    """`pip install .` into a fresh venv adds exactly `mcillum` and its
    dist-info to site-packages; the installed package, run from elsewhere,
    finds its scenes, plugins and the report's script. Offline: the wheel is built without build
    isolation and installed from the file (never `pip install --prefix` from
    this environment: pip would first uninstall this checkout's own install)."""
    build = tmp_path / "src"                       # a copy: the build leaves files behind
    shutil.copytree(ROOT, build, ignore=shutil.ignore_patterns(
        ".venv", ".git", "out", "build", "*.egg-info", "__pycache__", ".pytest_cache"))
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                           "--no-build-isolation", "--no-index", "-w", str(tmp_path / "dist"),
                           str(build)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    (wheel,) = (tmp_path / "dist").glob("mcillum-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    python = str(venv / "bin" / "python")
    site = _site_packages(python)
    before = set(os.listdir(site))
    done = subprocess.run([python, "-m", "pip", "install", "--quiet", "--no-deps",
                           "--no-index", str(wheel)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    added = set(os.listdir(site)) - before
    version = metadata.version("mcillum")
    assert added == {"mcillum", f"mcillum-{version}.dist-info"}, sorted(added)
    assert {"integrators", "envmaps", "validation", "scenes"} <= set(
        os.listdir(os.path.join(site, "mcillum")))
    assert (venv / "bin" / "mcillum").is_file()           # the console script
    # the dependencies come from this environment (its site-packages only:
    # no .pth there is read, so this checkout's editable mcillum stays out)
    result = subprocess.run([python, "-c", textwrap.dedent("""
        import mcillum, mitsuba as mi
        from mcillum.integrators.core import registry
        from mcillum.validation.plan import scenes
        from mcillum.validation.report import viewer   # its script is package data
        assert "DecompressionStream" in viewer.SCRIPT
        mi.set_variant("scalar_rgb")
        print(mcillum.__file__)
        print(scenes.index()["cornell_box"].path)
        print(" ".join(registry.names()))
        """)], cwd=tmp_path, capture_output=True, text=True, timeout=300,
        env={**os.environ, "PYTHONPATH": _site_packages(sys.executable)})
    assert result.returncode == 0, result.stderr
    package, cornell, names = result.stdout.strip().splitlines()[-3:]
    assert package.startswith(site) and cornell.startswith(site), result.stdout
    assert names.split() == registry.names()       # every family's folder was installed


#: The checkout's folders that are also importable as top-level packages.
FOLDERS = ("integrators", "envmaps", "validation")


def top_level_imports(root, folders=("mcillum", *FOLDERS, "tests")) -> list[str]:
    """``path:line name`` for every import of one of :data:`FOLDERS` as a
    top-level package in any module under ``folders`` of ``root``, subfolders
    included."""
    import ast

    bad = []
    for folder in folders:
        for path in sorted((root / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom)
                         and node.level == 0 else [])
                bad += [f"{path.relative_to(root)}:{node.lineno} {n}" for n in names
                        if n.split(".")[0] in FOLDERS]
    return bad


def test_no_module_imports_the_folders_as_top_level_packages():
    """Inside a checkout `integrators`, `envmaps` and `validation` are also
    importable as folders; importing them so would load a second copy of every
    plugin class. Every module imports them as mcillum.* (or relatively)."""
    assert not top_level_imports(ROOT)


def test_a_top_level_import_in_a_subfolder_is_caught(tmp_path):
    (tmp_path / "validation" / "stages").mkdir(parents=True)
    (tmp_path / "validation" / "stages" / "x.py").write_text("from validation import plan\n")
    (tmp_path / "integrators" / "mc").mkdir(parents=True)
    (tmp_path / "integrators" / "mc" / "y.py").write_text(
        "import os\n\ndef f():\n    import integrators.core.registry\n")
    (tmp_path / "integrators" / "mc" / "fine.py").write_text(
        "from ..core import registry\nfrom mcillum.integrators import mc\n")
    assert top_level_imports(tmp_path) == ["integrators/mc/y.py:4 integrators.core.registry",
                                           "validation/stages/x.py:1 validation"]


def test_tests_cannot_reach_off_this_machine():
    """The conftest guard refuses any address but the loopback before a
    packet leaves (192.0.2.1 is TEST-NET-1), and lets the loopback through."""
    import socket

    from conftest import OffMachineError
    for host in ("192.0.2.1", "example.org"):
        with pytest.raises(OffMachineError, match="loopback"):
            socket.create_connection((host, 9), timeout=0.1)
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", 9), timeout=0.5)
