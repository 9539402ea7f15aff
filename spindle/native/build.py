"""Build and load the C port (``spindle/native/c/*.c``) as a shared library, on first use.

The library is compiled once per source version, compiler flags and variant, into a cache
directory (``$PROPRIO_C_CACHE`` or ``~/.cache/proprio-elbow/c``), and loaded with ctypes.
Variants: ``"double"`` (matches the numpy core to round-off) and ``"float"`` (``-DPS_FLOAT``,
what a microcontroller without an FPU would run). ``sanitize=True`` adds AddressSanitizer
and UndefinedBehaviorSanitizer (for the fuzz tests; needs a compiler that has them).

The cache, and what is never done with it:

- The cache key is the sources (``c/*.c``, ``*.h``), the flags and the variant, not
  the compiler: a library built by one compiler is reused by any other, and a valid cache
  loads on a machine without a compiler. Changing ``$CC`` does not rebuild (empty the cache
  directory, or point ``$PROPRIO_C_CACHE`` elsewhere, to rebuild with another compiler).
- Each key has a small manifest, ``libproprio-<variant>-<key>.json``: the library's file name
  (which ends in the first hex digits of its SHA-256), its size in bytes, its SHA-256 and the
  compiler that built it. A library is loaded only after its size and SHA-256 match the
  manifest; a missing, truncated, zero-byte, garbage or altered library (or manifest) is
  rebuilt, never loaded (``dlopen`` of a truncated file can kill the interpreter with SIGBUS).
- A build compiles to a temporary file in the cache directory, checks that the compiler wrote
  something and that it loads as a library with the port's symbols (in a child process, so a
  bad file cannot crash this one), renames it into place, then writes the manifest, each
  atomically (``os.replace``). Concurrent first uses (e.g. AsyncVectorEnv workers) each
  build their own temporary file and replace the same names with identical, verified
  content: none ever loads a half-written file. A compiler that exits 0 but writes nothing,
  or writes something that is not a loadable library, raises :class:`CBackendError` naming
  the compiler; the temporary file is removed on any failure, and the leftovers of a build
  that was killed (its process is gone, or older than an hour) are removed by the next use.
- ``$CC`` may carry arguments (``CC="ccache gcc"``, ``CC="gcc -m64"``; split as a shell
  would, :func:`shlex.split`).

The ctypes mirrors of the header live in :mod:`spindle.native.abi`.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from functools import cache
from pathlib import Path

SOURCE_DIR = Path(__file__).resolve().parent / "c"
HEADER = SOURCE_DIR / "proprio.h"
VARIANTS = ("double", "float")
WARNING_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")
OPTIMISE_FLAGS = ("-O2", "-DPS_FAST_CBRT", "-DPS_CBRT_REFINE=1")
"""The host build: the Newton start's cube root from the bits and one refinement instead of
libm's cbrt (the start only needs to be near the root; Newton converges to the same
tolerance). Measured: 320 -> 275 ns per spindle step of the batch (864 spindles of the legs,
1 ms, x86-64 gcc -O2); -O3 and -march=native gave nothing beyond the noise, and a cached
library built with -march=native would not load on an older CPU sharing the cache (the batch
step's AVX2 lanes are a run-time choice inside the library instead)."""
FP_FLAGS = ("-ffp-contract=off", "-fno-trapping-math")
"""Every build: no contraction into fused multiply-adds (GCC's -std=c99 implies it, Clang's
default does not), so each operation rounds as the numpy core's does and the batch's SIMD
lanes (``ps_spindle_batch_step``) round as its scalar step does; FP exceptions are not
observed (the C port reports non-finite results by status), which lets the compiler turn the
lanes' per-lane branches into selects. Neither changes a value."""
SANITIZE_FLAGS = ("-O1", "-g", "-fsanitize=address,undefined", "-fno-omit-frame-pointer",
                  "-fno-sanitize-recover=all")
CACHE_FORMAT = 2
"""Part of the cache key: bump when the cache's layout or the manifest's meaning changes."""
REQUIRED_SYMBOLS = ("ps_spindle_step", "ps_chain_init", "ps_stim_step")
"""A freshly built library must export these (one per source file) to be cached."""
STALE_TMP_AGE_S = 3600.0
"""A temporary file older than this is a leftover whatever its name says (a build takes s)."""
TMP_PREFIX = "tmp-"


class CBackendError(RuntimeError):
    """The C library could not be built or loaded (no compiler, compile error, ...)."""


def sources() -> list[Path]:
    """The library's C sources (``c/*.c`` here; subdirectories are other targets)."""
    return sorted(SOURCE_DIR.glob("*.c"))


def compiler_command() -> list[str]:
    """The C compiler as a command: ``$CC`` split as a shell would (it may carry arguments,
    e.g. ``ccache gcc``), else ``cc``, ``gcc`` or ``clang``; its first word resolved on the
    PATH."""
    cc = os.environ.get("CC", "").strip()
    if cc:
        try:
            candidates = [shlex.split(cc)]
        except ValueError as exc:
            raise CBackendError(f"$CC={cc!r} is not a command line: {exc}") from None
    else:
        candidates = [["cc"], ["gcc"], ["clang"]]
    for argv in candidates:
        path = shutil.which(argv[0]) if argv else None
        if path:
            return [path, *argv[1:]]
    tried = f"$CC={cc!r}" if cc else "cc, gcc, clang"
    raise CBackendError(
        f"no C compiler found (tried {tried}); the 'c' backend compiles "
        "spindle/native/c/*.c on first use: install one (Debian: apt-get install gcc) or set $CC, "
        "or use backend='numpy'"
    )


def find_compiler() -> str:
    """The compiler's executable (the first word of :func:`compiler_command`, which callers
    that run the compiler should use: ``$CC`` may carry arguments)."""
    return compiler_command()[0]


def cache_dir() -> Path:
    root = os.environ.get("PROPRIO_C_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "proprio-elbow" / "c"


def compile_flags(variant: str = "double", sanitize: bool = False) -> list[str]:
    if variant not in VARIANTS:
        raise ValueError(f"variant={variant!r} is not one of {VARIANTS}")
    flags = [*WARNING_FLAGS, *FP_FLAGS, *(SANITIZE_FLAGS if sanitize else OPTIMISE_FLAGS),
             "-fPIC", "-shared"]
    if variant == "float":
        flags.append("-DPS_FLOAT")
    return flags


def library_path(variant: str = "double", sanitize: bool = False) -> Path:
    """The path of a verified shared library for ``variant``, built first if the cache has
    none or a bad one (see the module docstring). Needs a compiler only to build."""
    flags = compile_flags(variant, sanitize)
    srcs = sources()
    if not srcs:
        raise CBackendError(f"no C sources in {SOURCE_DIR}")
    directory = cache_dir()
    stem = f"libproprio-{variant}{'-san' if sanitize else ''}-{_cache_key(flags, srcs)[:16]}"
    manifest = directory / f"{stem}.json"
    _remove_stale_tmp(directory)
    path, fault = _verified(manifest, stem)
    if path is not None:
        return path
    try:
        compiler = compiler_command()
    except CBackendError as exc:
        raise CBackendError(f"{exc}\n(the cache {directory} cannot be used: {fault})") from None
    return _build(compiler, flags, srcs, directory, stem)


def _cache_key(flags: list[str], srcs: list[Path]) -> str:
    digest = hashlib.sha256(f"proprio-c-cache {CACHE_FORMAT}\0".encode())
    for flag in flags:
        digest.update(flag.encode() + b"\0")
    for path in sorted({*srcs, *SOURCE_DIR.glob("*.h")}):
        data = path.read_bytes()
        digest.update(f"{path.name}\0{len(data)}\0".encode() + data)
    return digest.hexdigest()


def _verified(manifest: Path, stem: str) -> tuple[Path | None, str]:
    """(the library ``manifest`` names, if it matches its size and SHA-256; else None and
    what is wrong). Reads the file, never maps it: a truncated file must not be dlopen'ed."""
    try:
        record = json.loads(manifest.read_text())
        name, size, sha256 = record["library"], record["size_bytes"], record["sha256"]
    except FileNotFoundError:
        return None, "no library built yet"
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return None, f"the manifest {manifest.name} is unreadable ({exc!r})"
    if (not isinstance(name, str) or Path(name).name != name or not name.startswith(stem)
            or not isinstance(size, int) or not isinstance(sha256, str)):
        return None, f"the manifest {manifest.name} is malformed"
    path = manifest.parent / name
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, f"the library {name} is unreadable ({exc.strerror})"
    if len(data) != size:
        return None, f"the library {name} has {len(data)} bytes, its manifest says {size}"
    if hashlib.sha256(data).hexdigest() != sha256:
        return None, f"the library {name} does not match its manifest's SHA-256"
    return path, ""


def _build(compiler: list[str], flags: list[str], srcs: list[Path], directory: Path,
           stem: str) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_file(directory, ".so")
    try:
        cmd = [*compiler, *flags, "-I", str(SOURCE_DIR), *map(str, srcs), "-o", str(tmp), "-lm"]
        result = subprocess.run(cmd, capture_output=True, text=True)
        if result.returncode != 0:
            raise CBackendError(
                f"compiling the C port failed ({shlex.join(cmd)}):\n{result.stderr}")
        data = tmp.read_bytes()
        if not data:
            raise CBackendError(
                f"the C compiler {shlex.join(compiler)} exited 0 but wrote nothing to "
                f"{tmp.name} (command: {shlex.join(cmd)})")
        problem = _load_problem(tmp)
        if problem:
            hint = (" (a sanitizer build loads only into a process started with the sanitizer "
                    "runtime, e.g. LD_PRELOAD=$(cc -print-file-name=libasan.so))"
                    if any(f.startswith("-fsanitize") for f in flags) else "")
            raise CBackendError(
                f"the C compiler {shlex.join(compiler)} exited 0 but its output is not a "
                f"loadable library with the port's symbols: {problem}{hint} "
                f"(command: {shlex.join(cmd)})")
        sha256 = hashlib.sha256(data).hexdigest()
        # The name carries the content's hash, so a manifest always names a file whose
        # content it describes, however concurrent builds interleave their replaces.
        library = directory / f"{stem}-{sha256[:12]}.so"
        tmp.chmod(0o755)  # mkstemp's 0600 would hide a shared cache from other users
        os.replace(tmp, library)
        record = {"library": library.name, "size_bytes": len(data), "sha256": sha256,
                  "compiler": compiler, "compiler_version": _version(compiler),
                  "flags": flags, "format": CACHE_FORMAT}
        tmp = _tmp_file(directory, ".json")
        tmp.write_text(json.dumps(record, indent=1) + "\n")
        tmp.chmod(0o644)
        os.replace(tmp, directory / f"{stem}.json")
    finally:
        tmp.unlink(missing_ok=True)
    return library


def _tmp_file(directory: Path, suffix: str) -> Path:
    """A new temporary file in ``directory`` whose name records this host and process."""
    fd, name = tempfile.mkstemp(dir=directory, prefix=f"{TMP_PREFIX}{_host_tag()}-{os.getpid()}-",
                                suffix=suffix)
    os.close(fd)
    return Path(name)


def _host_tag() -> str:
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def _remove_stale_tmp(directory: Path) -> None:
    """Remove the temporary files of builds that died: their process (on this host) is gone,
    or they are older than :data:`STALE_TMP_AGE_S` (e.g. another host's, or an earlier
    version's ``tmp*.so``). A live build's file is left alone."""
    try:
        candidates = [*directory.glob("tmp*.so"), *directory.glob(f"{TMP_PREFIX}*.json")]
    except OSError:
        return
    now = time.time()
    for path in candidates:
        parts = path.name.split("-")
        try:
            ours = len(parts) >= 4 and parts[1] == _host_tag() and parts[2].isdigit()
            if (ours and not _pid_alive(int(parts[2]))) or \
                    now - path.stat().st_mtime > STALE_TMP_AGE_S:
                path.unlink()
        except OSError:  # gone already, or a read-only cache: not this call's business
            pass


def _pid_alive(pid: int) -> bool:
    if os.name != "posix":  # os.kill(pid, 0) would terminate it on Windows
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


_PROBE = ("import ctypes, sys\n"
          "lib = ctypes.CDLL(sys.argv[1])\n"
          "missing = [s for s in sys.argv[2:] if not hasattr(lib, s)]\n"
          "sys.exit('missing symbols: ' + ', '.join(missing) if missing else 0)\n")


def _load_problem(path: Path) -> str:
    """Why ``path`` does not load as the port's library ("" if it does), found by loading it
    in a child process (a bad file can kill the process that maps it)."""
    result = subprocess.run([sys.executable, "-I", "-c", _PROBE, str(path), *REQUIRED_SYMBOLS],
                            capture_output=True, text=True)
    if result.returncode == 0:
        return ""
    if result.returncode < 0:
        return f"loading it killed a probe process with signal {-result.returncode}"
    lines = result.stderr.strip().splitlines()
    return lines[-1] if lines else f"the probe exited {result.returncode}"


def _version(compiler: list[str]) -> str:
    """The first line of ``compiler --version`` (for the manifest; "" if it has none)."""
    try:
        result = subprocess.run([*compiler, "--version"], capture_output=True, text=True,
                                timeout=30)
    except (OSError, subprocess.SubprocessError):
        return ""
    lines = result.stdout.strip().splitlines()
    return lines[0] if result.returncode == 0 and lines else ""


@cache
def load(variant: str = "double", sanitize: bool = False) -> ctypes.CDLL:
    """The loaded library (built on first use). Callers declare the prototypes they use."""
    return ctypes.CDLL(str(library_path(variant, sanitize)))
