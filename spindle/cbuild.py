"""Build and load the C port (``spindle/c/*.c``) as a shared library, on first use.

The library is compiled once per source version, compiler flags and variant, into a cache
directory (``$PROPRIO_C_CACHE`` or ``~/.cache/proprio-elbow/c``), and loaded with ctypes.
Variants: ``"double"`` (matches the numpy core to round-off) and ``"float"`` (``-DPS_FLOAT``,
what a microcontroller without an FPU would run). ``sanitize=True`` adds AddressSanitizer
and UndefinedBehaviorSanitizer (for the fuzz tests; needs a compiler that has them).

The ctypes mirrors of the header's structs live here, next to the loader, so every module
that binds part of the header shares one definition.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from functools import cache
from pathlib import Path

from spindle.params import SpindleParams

SOURCE_DIR = Path(__file__).resolve().parent / "c"
HEADER = SOURCE_DIR / "proprio.h"
VARIANTS = ("double", "float")
WARNING_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")
OPTIMISE_FLAGS = ("-O2",)
SANITIZE_FLAGS = ("-O1", "-g", "-fsanitize=address,undefined", "-fno-omit-frame-pointer",
                  "-fno-sanitize-recover=all")


class CBackendError(RuntimeError):
    """The C library could not be built or loaded (no compiler, compile error, ...)."""


def sources() -> list[Path]:
    """The library's C sources (``spindle/c/*.c``; subdirectories are other targets)."""
    return sorted(SOURCE_DIR.glob("*.c"))


def find_compiler() -> str:
    """The C compiler to use: ``$CC``, else ``cc``, ``gcc`` or ``clang`` on the PATH."""
    candidates = [os.environ["CC"]] if os.environ.get("CC") else ["cc", "gcc", "clang"]
    for name in candidates:
        path = shutil.which(name)
        if path:
            return path
    raise CBackendError(
        f"no C compiler found (tried {', '.join(candidates)}); the 'c' backend compiles "
        "spindle/c/*.c on first use: install one (Debian: apt-get install gcc) or set $CC, "
        "or use backend='numpy'"
    )


def cache_dir() -> Path:
    root = os.environ.get("PROPRIO_C_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "proprio-elbow" / "c"


def compile_flags(variant: str = "double", sanitize: bool = False) -> list[str]:
    if variant not in VARIANTS:
        raise ValueError(f"variant={variant!r} is not one of {VARIANTS}")
    flags = [*WARNING_FLAGS, *(SANITIZE_FLAGS if sanitize else OPTIMISE_FLAGS),
             "-fPIC", "-shared"]
    if variant == "float":
        flags.append("-DPS_FLOAT")
    return flags


def library_path(variant: str = "double", sanitize: bool = False) -> Path:
    """Build the shared library if needed and return its path."""
    compiler = find_compiler()
    flags = compile_flags(variant, sanitize)
    srcs = sources()
    if not srcs:
        raise CBackendError(f"no C sources in {SOURCE_DIR}")
    digest = hashlib.sha256()
    for part in (compiler, *flags):
        digest.update(part.encode() + b"\0")
    for path in (HEADER, *srcs):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    target = cache_dir() / f"libproprio-{variant}{'-san' if sanitize else ''}-" \
        f"{digest.hexdigest()[:16]}.so"
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    # Build beside the target and rename: concurrent first uses (e.g. AsyncVectorEnv
    # workers) never load a half-written file.
    fd, tmp = tempfile.mkstemp(dir=target.parent, suffix=".so")
    os.close(fd)
    cmd = [compiler, *flags, "-I", str(SOURCE_DIR), *map(str, srcs), "-o", tmp, "-lm"]
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        os.unlink(tmp)
        raise CBackendError(f"compiling the C port failed ({' '.join(cmd)}):\n{result.stderr}")
    os.replace(tmp, target)
    return target


@cache
def load(variant: str = "double", sanitize: bool = False) -> ctypes.CDLL:
    """The loaded library (built on first use). Callers declare the prototypes they use."""
    return ctypes.CDLL(str(library_path(variant, sanitize)))


def real_type(variant: str = "double") -> type:
    """The ctypes type of ``ps_real`` in ``variant``."""
    return ctypes.c_float if variant == "float" else ctypes.c_double


def structs(variant: str = "double") -> tuple[type, type]:
    """ctypes mirrors of (``ps_params``, ``ps_spindle``) for ``variant``.

    One pair of classes per variant however it is called (``structs()`` and
    ``structs("double")`` must agree, or ctypes refuses one's pointers where the other's are
    declared).
    """
    if variant not in VARIANTS:
        raise ValueError(f"variant={variant!r} is not one of {VARIANTS}")
    return _structs(variant)


@cache
def _structs(variant: str) -> tuple[type, type]:
    real = real_type(variant)
    fibre = real * 3

    class PsParams(ctypes.Structure):
        _fields_ = [(name, fibre) for name in PARAMS_FIELDS] + [("S", real)]

    class PsSpindle(ctypes.Structure):
        _fields_ = [("T", fibre), ("v", fibre), ("z", fibre), ("f", fibre),
                    ("L", real), ("gd", real), ("gs", real)]

    return PsParams, PsSpindle


# ps_params field -> spindle.FibreParams attribute, in the header's order.
PARAMS_FIELDS = {
    "KSR": "KSR_FU_L0", "KPR": "KPR_FU_L0", "M": "M_FU_s2_L0",
    "beta0": "beta0_FU_s_L0", "beta_drive": "beta_drive_FU_s_L0",
    "Gamma_drive": "Gamma_drive_FU", "CL": "CL", "CS": "CS", "R": "R_L0", "a": "a",
    "LSR0": "LSR0_L0", "LPR0": "LPR0_L0", "LNSR": "LNSR_L0", "LNPR": "LNPR_L0", "X": "X",
    "Lsec": "Lsec_L0", "G_pri": "G_primary_pps_L0", "G_sec": "G_secondary_pps_L0",
    "freq": "freq_pps", "p": "p", "tau": "tau_s",
}


def params_struct(params: SpindleParams, variant: str = "double") -> ctypes.Structure:
    """``params`` as a filled ``ps_params``."""
    PsParams, _ = structs(variant)
    out = PsParams()
    for field, attr in PARAMS_FIELDS.items():
        getattr(out, field)[:] = [getattr(f, attr) for f in params.fibres]
    out.S = params.S
    return out
