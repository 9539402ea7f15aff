"""Cross-build of the Cortex-M0+ firmware and its float32 host twin.

The firmware is ``spindle.c`` with ``c/m0plus/firmware.c`` (two muscles, HUMAN constants in
flash) for ``-mcpu=cortex-m0plus -mthumb``, soft float, newlib-nano; the host twin is the same
``spindle.c`` and options, float32, as a shared library, so the two compute the same numbers.
With ``Config.stim_dir`` the firmware also holds the fixed-point stimulator (``stimulation.c``,
:mod:`spindle.native.m0plus.stim`).
"""

from __future__ import annotations

import ctypes
import dataclasses
import hashlib
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from spindle.native import abi, fixed
from spindle.native import build as native_build
from spindle.params import HUMAN

C_DIR = native_build.SOURCE_DIR
FW_DIR = C_DIR / "m0plus"
TOOL_PREFIX = "arm-none-eabi-"
ARM_FLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wdouble-promotion",
             "-Os", "-mcpu=cortex-m0plus", "-mthumb", "-mfloat-abi=soft",
             "-ffunction-sections", "-fdata-sections", "-DPS_FLOAT"]
LINK_FLAGS = ["-nostartfiles", "--specs=nano.specs", "-Wl,--gc-sections", "-lm"]
PARAMS = HUMAN
"""The constants ``firmware.c`` holds in flash (the bench checks its bytes against these)."""
DEFAULT_STACK_BYTES = 0x400


@dataclasses.dataclass(frozen=True)
class Config:
    """One firmware build: one row of the lever table."""

    label: str
    step_s: float
    theta: float = 0.5
    plan: bool = False
    plan_in_flash: bool = False
    defines: tuple[str, ...] = ()
    fixed: bool = False  # ps_spindle_step_fx, its plan const in flash
    stim_dir: str = ""  # FW_STIM: the stimulator too, fw_stim_config.h from this folder

    def c_defines(self) -> list[str]:
        out = [f"-DFW_STEP_S={self.step_s!r}", f"-DFW_THETA={self.theta!r}",
               *(f"-D{d}" for d in self.defines)]
        if self.plan:
            out.append("-DFW_USE_PLAN")
        if self.plan_in_flash:
            out.append("-DFW_PLAN_IN_FLASH")
        if self.fixed:
            out.append("-DFW_FIXED")
        if self.stim_dir:
            out.append("-DFW_STIM")
        return out


def tool(name: str) -> str:
    """The path of ``arm-none-eabi-<name>``; exits naming the Debian packages if missing."""
    path = shutil.which(TOOL_PREFIX + name)
    if path is None:
        sys.exit(f"{TOOL_PREFIX}{name} not found: apt-get install -y gcc-arm-none-eabi "
                 "libnewlib-arm-none-eabi")
    return path


def key(*parts: object) -> str:
    """A file-name key of the parts and of the C sources (a rebuild after any edit)."""
    digest = hashlib.sha256(repr(parts).encode())
    for path in (*sorted(C_DIR.glob("*.h")), C_DIR / "spindle.c", C_DIR / "stimulation.c",
                 FW_DIR / "firmware.c", FW_DIR / "startup.c"):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def host_library(cfg: Config, build_dir: Path) -> ctypes.CDLL:
    """The same spindle.c and options, float32, as a host shared library."""
    out = build_dir / f"host_{key(cfg)}.so"
    if not out.exists():
        cmd = [*native_build.compiler_command(), *native_build.WARNING_FLAGS, "-O2", "-fPIC",
               "-shared", "-DPS_FLOAT", *cfg.c_defines(), "-I", str(C_DIR),
               str(C_DIR / "spindle.c"), "-o", str(out), "-lm"]
        subprocess.run(cmd, check=True)
    lib = ctypes.CDLL(str(out))
    PsParams, PsSpindle = abi.structs("float")
    PsPlan = abi.plan_struct("float")
    P, f = ctypes.POINTER, ctypes.c_float
    lib.ps_spindle_init.argtypes = [P(PsSpindle), P(PsParams), f, f, f]
    lib.ps_spindle_step.argtypes = [P(PsSpindle), P(PsParams), f, f, f, f, f, P(f), P(f)]
    lib.ps_plan_init.argtypes = [P(PsPlan), P(PsParams), f, f]
    lib.ps_spindle_step_plan.argtypes = [P(PsSpindle), P(PsPlan), f, f, f, P(f), P(f)]
    lib.ps_spindle_afferents.argtypes = [P(PsSpindle), P(PsParams), P(f), P(f)]
    lib.ps_spindle_afferents.restype = None
    fixed.declare_fixed(lib, "float")
    return lib


def fixed_plan(lib: ctypes.CDLL, cfg: Config) -> ctypes.Structure:
    """The ``ps_plan_fx`` of the firmware's constants at the configuration's step."""
    return fixed.make_plan(lib, PARAMS, cfg.step_s, cfg.theta, "float")


def _float_literal(x: float) -> str:
    return f"{float(np.float32(x)).hex()}f"


def _initializer(plan: ctypes.Structure, scalar) -> str:
    """The struct's fields, in order, as a C initializer list (``scalar`` formats one; nested
    structs and arrays of them are braced in turn)."""
    def value_source(ctype, value) -> str:
        if issubclass(ctype, ctypes.Structure):
            return "{" + _initializer(value, scalar) + "}"
        if issubclass(ctype, ctypes.Array):
            return "{" + ", ".join(value_source(ctype._type_, v) for v in value) + "}"
        return scalar(ctype, value)

    return ",\n    ".join(value_source(ctype, getattr(plan, name))
                          for name, ctype in type(plan)._fields_)


def _write_header(build_dir: Path, cfg: Config, name: str, text: str) -> Path:
    path = build_dir / f"{name}_{key(cfg)}" / f"fw_{name}.h"
    path.parent.mkdir(exist_ok=True)
    path.write_text(text)
    return path


def plan_header(cfg: Config, build_dir: Path) -> Path:
    """fw_plan.h: the plan of ps_plan_init (host, float32) as a const initializer."""
    lib = host_library(cfg, build_dir)
    plan = abi.plan_struct("float")()
    params = abi.params_struct(PARAMS, "float")
    code = lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(params), cfg.step_s, cfg.theta)
    if code != abi.Status.PS_OK:
        raise RuntimeError(f"ps_plan_init: {abi.status_name(code)}")

    def scalar(ctype, value) -> str:
        return str(int(value)) if ctype is ctypes.c_int else _float_literal(value)

    return _write_header(build_dir, cfg, "plan",
                         "/* generated by spindle.native.m0plus.build from ps_plan_init */\n"
                         "const ps_plan fw_plan = {\n    " + _initializer(plan, scalar)
                         + "\n};\n")


def plan_fx_header(cfg: Config, build_dir: Path) -> Path:
    """fw_plan_fx.h: the plan of ps_plan_fx_init (host) as a const initializer."""
    plan = fixed_plan(host_library(cfg, build_dir), cfg)
    return _write_header(build_dir, cfg, "plan_fx",
                         "/* generated by spindle.native.m0plus.build from ps_plan_fx_init */\n"
                         "const ps_plan_fx fw_plan_fx = {\n    "
                         + _initializer(plan, lambda _ctype, value: f"{int(value)}L")
                         + "\n};\n")


def build_firmware(cfg: Config, build_dir: Path,
                   stack_bytes: int = DEFAULT_STACK_BYTES) -> Path:
    """The firmware ELF of ``cfg`` with ``stack_bytes`` reserved for the stack."""
    elf = build_dir / f"fw_{key(cfg, stack_bytes)}.elf"
    extra = []
    if cfg.plan_in_flash:
        extra = ["-I", str(plan_header(cfg, build_dir).parent)]
    if cfg.fixed:
        extra = ["-I", str(plan_fx_header(cfg, build_dir).parent)]
    if cfg.stim_dir:  # the stimulator's entry points are roots for --gc-sections too
        extra += ["-I", cfg.stim_dir, str(C_DIR / "stimulation.c"),
                  "-Wl,--undefined=fw_stim_init", "-Wl,--undefined=fw_stim_step"]
    cmd = [tool("gcc"), *ARM_FLAGS, *cfg.c_defines(), "-I", str(C_DIR), *extra,
           str(C_DIR / "spindle.c"), str(FW_DIR / "firmware.c"), str(FW_DIR / "startup.c"),
           "-T", str(FW_DIR / "m0plus.ld"),
           f"-Wl,--defsym=FW_STACK_SIZE={stack_bytes}", *LINK_FLAGS, "-o", str(elf)]
    subprocess.run(cmd, check=True)
    return elf


def sizes(elf: Path) -> tuple[int, int]:
    """(flash, RAM) bytes from arm-none-eabi-size: text + data, data + bss."""
    out = subprocess.run([tool("size"), str(elf)], check=True, capture_output=True,
                         text=True).stdout.splitlines()[1].split()
    text, data, bss = (int(x) for x in out[:3])
    return text + data, data + bss


def symbols(elf: Path) -> dict[str, tuple[int, int]]:
    """name -> (address, size) of the ELF's symbols (arm-none-eabi-nm -S)."""
    out = subprocess.run([tool("nm"), "-S", str(elf)], check=True, capture_output=True,
                         text=True).stdout
    table = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 4:
            table[parts[3]] = (int(parts[0], 16), int(parts[1], 16))
        elif len(parts) == 3:
            table[parts[2]] = (int(parts[0], 16), 0)
    return table
