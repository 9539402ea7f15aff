"""The C build cache (spindle/build.py) under faults: a bad cached library is rebuilt, never
loaded; a compiler that writes nothing or junk is a clear error and caches nothing; ``$CC``
may carry arguments; a killed build leaves nothing behind; a valid cache loads without a
compiler; concurrent builds do not corrupt each other.

One real compile for the whole module: the fixture builds the library once through ``fakecc``,
a ccache-like launcher that logs every call and afterwards serves that library (a copy, in
milliseconds) wherever it is told to write. Loads run in a child process, so a library that
kills its loader (SIGBUS on a truncated file) fails the test instead of ending the run.
"""

from __future__ import annotations

import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from spindle.native import build

try:
    build.find_compiler()
except build.CBackendError as exc:  # pragma: no cover - depends on the machine
    pytest.skip(str(exc), allow_module_level=True)

REPO = Path(build.__file__).resolve().parents[2]  # the project root (it was spindle/)

FAKECC = r"""#!/bin/sh
# ccache-like launcher: fakecc [compiler] flags... (logs each compile; serves the stored build)
for a in "$@"; do [ "$a" = "--version" ] && { echo "fakecc 1"; exit 0; }; done
echo "$*" >> "${FAKECC_LOG:-/dev/null}"
out=""; prev=""
for a in "$@"; do [ "$prev" = "-o" ] && out="$a"; prev="$a"; done
case "$1" in -*) cc=gcc ;; *) cc="$1"; shift ;; esac
sleep "${FAKECC_SLEEP_S:-0}"
if [ -s "$STORE" ]; then cp "$STORE" "$out"; exit 0; fi
"$cc" "$@" && cp "$out" "$STORE"
"""

# ps_chebval(0.5, [1, 2, 3]) = 1 + 2*0.5 + 3*(2*0.5**2 - 1) = 0.5: the loaded library works.
CHILD = """
import ctypes
from spindle.native import abi, build
lib = build.load("double")
lib.ps_chebval.restype = ctypes.c_double
lib.ps_chebval.argtypes = [ctypes.c_double, ctypes.POINTER(ctypes.c_double), ctypes.c_int]
print(lib.ps_chebval(0.5, (ctypes.c_double * 3)(1.0, 2.0, 3.0), 3))
"""


def script(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(0o755)
    return path


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict:
    """A cache with one real build of the double library, and the launcher that built it."""
    root = tmp_path_factory.mktemp("cbuild")
    store = root / "store.so"
    fakecc = script(root / "fakecc", FAKECC.replace("$STORE", shlex.quote(str(store))))
    cache = root / "cache"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PROPRIO_C_CACHE", str(cache))
        mp.setenv("CC", shlex.quote(str(fakecc)))
        mp.setenv("FAKECC_LOG", str(root / "build.log"))
        build.library_path("double")
    assert store.stat().st_size > 0
    return {"cache": cache, "store": store, "fakecc": fakecc}


@pytest.fixture
def env(built, tmp_path, monkeypatch) -> dict:
    """This test's environment: an empty cache, ``fakecc`` as $CC, a log of its compiles."""
    values = {"PROPRIO_C_CACHE": str(tmp_path / "cache"), "CC": shlex.quote(str(built["fakecc"])),
              "FAKECC_LOG": str(tmp_path / "cc.log")}
    for name, value in values.items():
        monkeypatch.setenv(name, value)
    return values


def copy_cache(built, env) -> Path:
    return Path(shutil.copytree(built["cache"], env["PROPRIO_C_CACHE"]))


def compiles(env) -> list[str]:
    log = Path(env["FAKECC_LOG"])
    return log.read_text().splitlines() if log.exists() else []


def load_in_child(env, *, script: str = CHILD, **extra: str) -> subprocess.CompletedProcess:
    child_env = {**os.environ, **env, **extra,
                 "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", script], env=child_env, capture_output=True,
                          text=True, timeout=120)


def assert_loaded(result: subprocess.CompletedProcess) -> None:
    assert result.returncode == 0, (result.returncode, result.stderr[-2000:])
    assert float(result.stdout) == 0.5


def assert_clean_cache(cache: Path, good: bytes) -> None:
    """Every library in the cache is the good build; no temporary file is left."""
    names = sorted(p.name for p in cache.iterdir())
    assert not [n for n in names if n.startswith("tmp")], names
    libraries = sorted(cache.glob("*.so"))
    assert libraries and all(p.read_bytes() == good for p in libraries), names


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def garbage(path: Path) -> None:
    path.write_bytes(b"not a library\n" * 100)


def empty(path: Path) -> None:
    path.write_bytes(b"")


def flip_a_byte(path: Path) -> None:  # same size, different content: only a checksum sees it
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def library_of(cache: Path) -> Path:
    (library,) = cache.glob("*.so")
    return library


def manifest_of(cache: Path) -> Path:
    (manifest,) = cache.glob("*.json")
    return manifest


@pytest.mark.parametrize("fault, target", [
    (truncate, library_of), (garbage, library_of), (empty, library_of),
    (flip_a_byte, library_of), (garbage, manifest_of),
], ids=["truncated", "garbage", "zero-bytes", "checksum-mismatch", "garbage-manifest"])
def test_a_bad_cached_library_is_rebuilt_not_loaded(built, env, fault, target):
    cache = copy_cache(built, env)
    fault(target(cache))
    assert_loaded(load_in_child(env))  # the interpreter survives (no SIGBUS, no OSError)
    assert len(compiles(env)) == 1
    assert_clean_cache(cache, built["store"].read_bytes())
    build.library_path("double")  # and the rebuilt cache is used as it is
    assert len(compiles(env)) == 1


@pytest.mark.parametrize("compiler, error", [
    ("true", r"compiler \S*true exited 0 but wrote nothing"),
    ("junkcc", r"compiler \S*junkcc exited 0 but its output is not a loadable library"),
])
def test_a_compiler_that_writes_nothing_or_junk_is_a_clear_error(built, env, monkeypatch,
                                                                  tmp_path, compiler, error):
    script(tmp_path / "junkcc", '#!/bin/sh\nfor a; do [ "$p" = -o ] && o="$a"; p="$a"; done\n'
                                'echo junk > "$o"\n')
    monkeypatch.setenv("CC", compiler if compiler == "true" else str(tmp_path / "junkcc"))
    with pytest.raises(build.CBackendError, match=error):
        build.library_path("double")
    cache = Path(env["PROPRIO_C_CACHE"])
    assert list(cache.iterdir()) == []  # nothing cached, no temporary file left
    monkeypatch.setenv("CC", env["CC"])  # a working compiler then builds it
    assert build.library_path("double").read_bytes() == built["store"].read_bytes()
    assert len(compiles(env)) == 1


def test_cc_with_arguments_is_honoured(built, env, monkeypatch, tmp_path):
    # like CC="ccache gcc -m64", with the launcher in a directory whose name has a space
    launcher = tmp_path / "dir with space" / "fakecc"
    launcher.parent.mkdir()
    shutil.copy2(built["fakecc"], launcher)
    monkeypatch.setenv("CC", f"{shlex.quote(str(launcher))} gcc -m64")
    assert build.library_path("double").read_bytes() == built["store"].read_bytes()
    (call,) = compiles(env)
    assert call.startswith("gcc -m64 -std=c99 ")


def test_a_killed_build_leaves_nothing_behind(built, env, tmp_path):
    cache = Path(env["PROPRIO_C_CACHE"])
    cache.mkdir()
    slowcc = script(tmp_path / "slowcc", '#!/bin/sh\nfor a; do [ "$p" = -o ] && o="$a"; p="$a"; '
                                         'done\nprintf "\\177ELF partial" > "$o"\nexec sleep 60\n')
    child_env = {**os.environ, **env, "CC": str(slowcc),
                 "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    child = subprocess.Popen([sys.executable, "-c", CHILD], env=child_env,
                             start_new_session=True, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    try:
        # polls counted, not timed: the partial library appears after the child's import and
        # the fake compiler's first write: measured 18-30 polls (load average 7 on 2 cores)
        for _ in range(500):
            if [p for p in cache.glob("tmp*.so") if p.stat().st_size > 0]:
                break
            assert child.poll() is None
            time.sleep(0.02)
        else:
            pytest.fail("the slow compiler never wrote its partial library (500 polls)")
    finally:
        os.killpg(child.pid, signal.SIGKILL)  # the build dies part-way, compiler and all
        child.wait()
    old = cache / "tmpk3x9q1.so"  # and an earlier version's leftover, two hours old
    old.write_bytes(b"\x7fELF partial")
    os.utime(old, (time.time() - 7200, time.time() - 7200))
    assert len(list(cache.glob("tmp*"))) == 2
    assert build.library_path("double").read_bytes() == built["store"].read_bytes()
    assert_clean_cache(cache, built["store"].read_bytes())


def test_a_valid_cache_loads_without_a_compiler(built, env, tmp_path, monkeypatch):
    cache = copy_cache(built, env)
    nothing = tmp_path / "empty-bin"
    nothing.mkdir()
    for cc in ("/nonexistent/cc", ""):  # a $CC that is not there, and none at all
        assert_loaded(load_in_child(env, CC=cc, PATH=str(nothing)))
    assert compiles(env) == []
    # a bad cache without a compiler: the error names both
    truncate(library_of(cache))
    monkeypatch.setenv("CC", "/nonexistent/cc")
    error = r"(?s)no C compiler.*backend='numpy'.*cannot be used: the library \S+ has \d+ bytes"
    with pytest.raises(build.CBackendError, match=error):
        build.library_path("double")


def test_concurrent_builds_do_not_corrupt_each_other(built, env):
    children = [subprocess.Popen([sys.executable, "-c", CHILD], text=True,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 env={**os.environ, **env, "FAKECC_SLEEP_S": "0.3",
                                      "PYTHONPATH": os.pathsep.join(
                                          [str(REPO), os.environ.get("PYTHONPATH", "")])})
                for _ in range(2)]
    for child in children:
        out, err = child.communicate(timeout=120)
        assert child.returncode == 0 and float(out) == 0.5, err[-2000:]
    assert 1 <= len(compiles(env)) <= 2
    cache = Path(env["PROPRIO_C_CACHE"])
    assert_clean_cache(cache, built["store"].read_bytes())
    done = len(compiles(env))
    assert_loaded(load_in_child(env))  # the cache they left is valid as it is
    assert len(compiles(env)) == done


# A child that asks for the C backend both ways: "c" must name the cache, "auto" falls back.
BACKEND_CHILD = """
import numpy as np
import spindle
from spindle.backends import resolve_backend
from spindle.native.build import CBackendError
print(resolve_backend("auto"))
try:
    spindle.simulate(np.ones(3), 1e-3, backend="c")
except CBackendError as exc:
    print("CBackendError:", exc)
"""


def _file_in_place(cache: Path) -> None:
    cache.write_text("not a folder\n")


def _file_as_parent(cache: Path) -> Path:
    cache.write_text("not a folder\n")
    return cache / "sub"


def _read_only(cache: Path) -> None:
    cache.mkdir()
    cache.chmod(0o555)


@pytest.mark.parametrize("make_bad", [_file_in_place, _file_as_parent, pytest.param(
    _read_only, marks=pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere"))],
    ids=["file-in-place", "file-as-parent", "read-only"])
def test_an_unwritable_cache_is_a_clear_error_and_auto_falls_back(env, tmp_path, make_bad):
    """A raw FileExistsError / NotADirectoryError / PermissionError naming a temp file used
    to come out of ``backend="c"``; ``"auto"`` fell back to numpy and still must."""
    cache = tmp_path / "bad-cache"
    cache = make_bad(cache) or cache
    env = {**env, "PROPRIO_C_CACHE": str(cache)}
    result = load_in_child(env, script=BACKEND_CHILD)
    assert result.returncode == 0, result.stderr[-2000:]
    first, *rest = result.stdout.splitlines()
    assert first == "numpy"
    assert len(rest) == 1 and rest[0].startswith("CBackendError: the C cache " + str(cache))
    assert "$PROPRIO_C_CACHE" in rest[0] and "tmp-" not in rest[0]
    assert compiles(env) == []


def test_a_cache_that_refuses_new_files_is_a_clear_error(env, tmp_path, monkeypatch):
    """The read-only case for a process that may write anywhere (root): the cache folder
    exists but creating the build's temporary file there is refused."""
    cache = tmp_path / "cache"
    cache.mkdir()
    monkeypatch.setenv("PROPRIO_C_CACHE", str(cache))

    def refuse(*args, dir=None, **kwargs):
        raise PermissionError(13, "Permission denied", str(Path(dir) / "tmp-xyz.so"))

    monkeypatch.setattr(build.tempfile, "mkstemp", refuse)
    with pytest.raises(build.CBackendError, match=rf"the C cache {cache} cannot be written "
                       r"\(Permission denied.*\$PROPRIO_C_CACHE"):
        build.library_path("double")
    assert list(cache.iterdir()) == []
