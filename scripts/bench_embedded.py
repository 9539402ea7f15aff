"""Cost of the C spindle on a Cortex-M0+: instructions per step, MIPS, flash and RAM.

Cross-compiles spindle/native/c/spindle.c with the firmware spindle/native/c/m0plus/firmware.c (two
muscles, HUMAN constants in flash) for -mcpu=cortex-m0plus -mthumb, soft float, newlib-nano,
and runs the step in an instruction-set emulator (unicorn >= 2.1) on the Mileusnic Fig. 3
protocol (ramps 0.95 -> 1.08 L0 at 0.11, 0.66, 1.55 L0/s, drive (0,0), (70,0), (0,70) pps,
3.3 s), sampled once per spindle step. For every configuration of the lever table it prints
the executed instructions per step, MIPS per muscle (instructions per step / step), flash and
RAM of the firmware (arm-none-eabi-size: flash = text + data, RAM = data + bss including the
reserved stack, whose high-water mark is measured in the emulator) and the accuracy: the
worst-run RMS of Ia and II against the stiff reference (spindle.reference, scipy Radau).

Instruction-set check: unicorn opened in M-class mode silently models a Cortex-M33 (its CPU
model cannot be changed there, and sdiv runs). The emulator is therefore opened in Thumb
mode with the Cortex-M0 model (ARMv6-M), and the script checks that sdiv and a Thumb-2
32-bit data-processing instruction do fault. That model still executes cbz/cbnz and it
(ARMv7-M only), so every executed instruction is also decoded with the ARMv6-M encoding
rules, and the whole binary is disassembled with arm-none-eabi-objdump and checked the same
way; any ARMv7-M-only instruction is an error.

The emulated rates are compared with a host build of the same sources and options (all
float32, no libm call on the measured path when PS_FAST_CBRT is set, so they agree to the
bit); the accuracy of each configuration is measured on the host build over all 9 runs.

The last rows are the fixed-point step (ps_spindle_step_fx, int32 Q24, firmware option
FW_FIXED): its plan is made on the host by ps_plan_fx_init from spindle.HUMAN and compiled
into the firmware as a const; lengths go to the firmware in Q24 and drives in Q8, rates come
back in Q16 (the host build gets the same rounded inputs, and the two agree to the bit).

A second input, the demo motion, measures the fixed-point step as the prosthesis runs it:
the Fig. 3 protocol holds the fusimotor drive constant within a run, so the step reuses its
activation targets there. The demo motion is the seed paper's repeated rapid elbow
flexion-extension (triangle 20-110 deg at 130 deg/s, proprio_env.servo_motion.triangle_deg)
through the numpy chain (spindle.chain.run_chain, ChainConfig()) sampled once per spindle step
(5 ms); the BRA and TRImed lengths and the chain's own gamma_s, gamma_d of every step are fed
to the two-muscle firmware. It prints the instructions per step per muscle, MIPS per muscle,
the costliest step, the same lengths with the drives held (the cost of the activation-target
divides), and the RMS of the fixed-point rates against the double ps_spindle_step at the same
step and inputs, and against the chain's own rates (numpy, trapezoidal 1 ms). Its summary
line `demo_mips_per_muscle=... demo_peak_mips=... demo_rms_vs_double_pps=...` precedes the
last line, which stays the Fig. 3 figure.

Usage:
    PYTHONPATH=. python scripts/bench_embedded.py            # all levers, all 9 runs (~10 min)
    PYTHONPATH=. python scripts/bench_embedded.py --quick    # final configuration, 2 runs
Needs: gcc-arm-none-eabi, libnewlib-arm-none-eabi, a host C compiler, unicorn, scipy.
The last line reads
    m0plus_mips_per_muscle=<float> rms_pps=<float> flash_bytes=<int> ram_bytes=<int>
for the cheapest measured configuration within RMS_TARGET_PPS (2 pps; --quick measures only
the final one, the fixed-point step at 5 ms).
"""

from __future__ import annotations

import argparse
import bisect
import collections
import ctypes
import dataclasses
import functools
import hashlib
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import spindle
from spindle.native import abi, build
from spindle.native import spindle as native_spindle

REPO = Path(__file__).resolve().parents[1]
C_DIR = build.SOURCE_DIR
FW_DIR = C_DIR / "m0plus"
TOOL_PREFIX = "arm-none-eabi-"
ARM_FLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wdouble-promotion",
             "-Os", "-mcpu=cortex-m0plus", "-mthumb", "-mfloat-abi=soft",
             "-ffunction-sections", "-fdata-sections", "-DPS_FLOAT"]
LINK_FLAGS = ["-nostartfiles", "--specs=nano.specs", "-Wl,--gc-sections", "-lm"]
PARAMS = spindle.HUMAN
SPEEDS = (0.11, 0.66, 1.55)
DRIVES = ((0.0, 0.0), (70.0, 0.0), (0.0, 70.0))
DURATION_S = 3.3
REFERENCE_DT_S = 1e-3
QUICK_RUNS = ((1.55, 70.0, 0.0), (0.66, 0.0, 70.0))
STACK_PATTERN = 0xA5
RMS_TARGET_PPS = 2.0


@dataclasses.dataclass(frozen=True)
class Config:
    """One row of the lever table."""

    label: str
    step_s: float
    theta: float = 0.5
    plan: bool = False
    plan_in_flash: bool = False
    defines: tuple[str, ...] = ()
    fixed: bool = False  # ps_spindle_step_fx, its plan const in flash

    def c_defines(self) -> list[str]:
        out = [f"-DFW_STEP_S={self.step_s!r}", f"-DFW_THETA={self.theta!r}",
               *(f"-D{d}" for d in self.defines)]
        if self.plan:
            out.append("-DFW_USE_PLAN")
        if self.plan_in_flash:
            out.append("-DFW_PLAN_IN_FLASH")
        if self.fixed:
            out.append("-DFW_FIXED")
        return out


FAST = ("PS_FAST_CBRT", "PS_CBRT_REFINE=1")
LOOSE = ("PS_NEWTON_TOL_Z=1e-3",)
LEVERS = [
    Config("forward Euler, z = powf(|v|, 0.1) (orientation)", 1e-3, theta=0.0),
    Config("trapezoidal, z = sgn(v)|v|^0.1 (no powf), Newton to 2e-6", 1e-3),
    Config("+ plan: derived constants, reciprocals, bounded Newton start", 1e-3, plan=True),
    Config("+ cube root without libm (PS_FAST_CBRT)", 1e-3, plan=True, defines=FAST),
    Config("+ Newton tolerance 1e-3 in z (PS_NEWTON_TOL_Z)", 1e-3, plan=True,
           defines=(*FAST, *LOOSE)),
    Config("  fixed 2 Newton iterations instead (PS_NEWTON_ITER=2)", 1e-3, plan=True,
           defines=(*FAST, "PS_NEWTON_ITER=2")),
    Config("  tolerance 1e-3 at a 2 ms step", 2e-3, plan=True, defines=(*FAST, *LOOSE)),
    Config("  tolerance 1e-3 at a 3 ms step", 3e-3, plan=True, defines=(*FAST, *LOOSE)),
    Config("  tolerance 1e-3 at a 5 ms step", 5e-3, plan=True, defines=(*FAST, *LOOSE)),
    Config("+ plan const in flash (5 ms)", 5e-3, plan=True, plan_in_flash=True,
           defines=(*FAST, *LOOSE)),
    Config("  fixed point at a 3 ms step", 3e-3, fixed=True),
    Config("fixed point: int32 Q24 step (ps_spindle_step_fx), plan in flash (5 ms)", 5e-3,
           fixed=True),
]
FINAL = LEVERS[-1]


# ---- building ---------------------------------------------------------------------------

def tool(name: str) -> str:
    path = shutil.which(TOOL_PREFIX + name)
    if path is None:
        sys.exit(f"{TOOL_PREFIX}{name} not found: apt-get install -y gcc-arm-none-eabi "
                 "libnewlib-arm-none-eabi")
    return path


def key(*parts: object) -> str:
    """A file-name key of the parts and of the C sources (a rebuild after any edit)."""
    digest = hashlib.sha256(repr(parts).encode())
    for path in (C_DIR / "proprio.h", C_DIR / "spindle.c", FW_DIR / "firmware.c"):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def host_library(cfg: Config, build_dir: Path) -> ctypes.CDLL:
    """The same spindle.c and options, float32, as a host shared library."""
    out = build_dir / f"host_{key(cfg)}.so"
    if not out.exists():
        cmd = [*build.compiler_command(), *build.WARNING_FLAGS, "-O2", "-fPIC", "-shared",
               "-DPS_FLOAT", *cfg.c_defines(), "-I", str(C_DIR), str(C_DIR / "spindle.c"),
               "-o", str(out), "-lm"]
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
    declare_fixed(lib, "float")
    return lib


FX_Q24, FX_DRIVE, FX_RATE = 1 << 24, 256, 1 << 16
FX_ROOT_TABLE = 31


@functools.cache
def fixed_structs() -> tuple[type, type]:
    """ctypes mirrors of ps_plan_fx and ps_spindle_fx (proprio.h, fixed-point step)."""
    i32, n = ctypes.c_int32, 3

    class PsPlanFx(ctypes.Structure):
        _fields_ = ([(k, i32) for k in ("max_dL", "theta", "one_minus_theta", "th_h", "S",
                                         "tol", "y_max", "v_max", "dg_shift")]
                    + [(k, i32 * n) for k in (
                        "KSR", "inv_KSR", "inv_k1", "c_f0", "c_a0", "c_a1", "freq",
                        "beta0", "beta_drive", "Gamma_drive", "CL", "CS", "KPR", "LPR0", "R",
                        "LSR0", "LSR0_R", "LSR0_LPR0", "c_Av", "a2", "inv_a2", "r_cap", "M_h",
                        "th_h_KSR", "th_k1", "th_KPR", "th_CL", "th_CS", "stretch0", "G_pri",
                        "c_sec1", "c_sec2", "sec_off")]
                    + [("root10", i32 * FX_ROOT_TABLE)])

    class PsSpindleFx(ctypes.Structure):
        _fields_ = ([(k, i32 * n) for k in ("T", "v", "z", "f", "target")]
                    + [(k, i32) for k in ("L", "gd", "gs")])

    return PsPlanFx, PsSpindleFx


def declare_fixed(lib: ctypes.CDLL, variant: str) -> None:
    """Prototypes of the fixed-point functions in a host build of spindle.c."""
    PsPlanFx, PsSpindleFx = fixed_structs()
    PsParams, _ = abi.structs(variant)
    P, i32 = ctypes.POINTER, ctypes.c_int32
    real = abi.real_type(variant)
    lib.ps_plan_fx_init.argtypes = [P(PsPlanFx), P(PsParams), real, real]
    lib.ps_spindle_fx_init.argtypes = [P(PsSpindleFx), P(PsPlanFx), i32, i32, i32]
    lib.ps_spindle_step_fx.argtypes = [P(PsSpindleFx), P(PsPlanFx), i32, i32, i32, P(i32),
                                       P(i32)]
    lib.ps_spindle_fx_afferents.argtypes = [P(PsSpindleFx), P(PsPlanFx), P(i32), P(i32)]
    lib.ps_spindle_fx_afferents.restype = None


def fixed_rates(lib: ctypes.CDLL, plan, L: np.ndarray, gd: np.ndarray,
                gs: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Ia, II (pps) of the fixed-point step along L (L0), gd, gs (pps), starting at rest at
    L[0]; (ia, ii, status): on a failing step the rest is NaN and its status is returned."""
    _, PsSpindleFx = fixed_structs()
    s = PsSpindleFx()
    q24 = np.round(np.asarray(L, dtype=np.float64) * FX_Q24).astype(np.int64)
    dgd = np.round(np.broadcast_to(gd, L.shape) * FX_DRIVE).astype(np.int64)
    dgs = np.round(np.broadcast_to(gs, L.shape) * FX_DRIVE).astype(np.int64)
    ia = np.full(len(L), np.nan)
    ii = np.full(len(L), np.nan)
    code = lib.ps_spindle_fx_init(ctypes.byref(s), ctypes.byref(plan), int(q24[0]),
                                  int(dgd[0]), int(dgs[0]))
    if code != abi.Status.PS_OK:
        return ia, ii, code
    a, b = ctypes.c_int32(), ctypes.c_int32()
    lib.ps_spindle_fx_afferents(ctypes.byref(s), ctypes.byref(plan), ctypes.byref(a),
                                ctypes.byref(b))
    ia[0], ii[0] = a.value / FX_RATE, b.value / FX_RATE
    for j in range(1, len(L)):
        code = lib.ps_spindle_step_fx(ctypes.byref(s), ctypes.byref(plan), int(q24[j]),
                                      int(dgd[j]), int(dgs[j]), ctypes.byref(a),
                                      ctypes.byref(b))
        if code != abi.Status.PS_OK:
            return ia, ii, code
        ia[j], ii[j] = a.value / FX_RATE, b.value / FX_RATE
    return ia, ii, 0


def plan_header(cfg: Config, build_dir: Path) -> Path:
    """fw_plan.h: the plan of ps_plan_init (host, float32) as a const initializer."""
    lib = host_library(cfg, build_dir)
    PsPlan = abi.plan_struct("float")
    plan = PsPlan()
    params = abi.params_struct(PARAMS, "float")
    code = lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(params), cfg.step_s, cfg.theta)
    if code != abi.Status.PS_OK:
        raise RuntimeError(f"ps_plan_init: {abi.status_name(code)}")

    def literal(x: float) -> str:
        return f"{float(np.float32(x)).hex()}f"

    parts = []
    for name, ctype in PsPlan._fields_:
        value = getattr(plan, name)
        if ctype is ctypes.c_int:
            parts.append(str(int(value)))
        elif ctype is ctypes.c_float:
            parts.append(literal(value))
        elif ctype._type_ is ctypes.c_int:
            parts.append("{" + ", ".join(str(int(v)) for v in value) + "}")
        else:
            parts.append("{" + ", ".join(literal(v) for v in value) + "}")
    path = build_dir / f"plan_{key(cfg)}" / "fw_plan.h"
    path.parent.mkdir(exist_ok=True)
    path.write_text("/* generated by scripts/bench_embedded.py from ps_plan_init */\n"
                    "const ps_plan fw_plan = {\n    " + ",\n    ".join(parts) + "\n};\n")
    return path


def fixed_plan(lib: ctypes.CDLL, cfg: Config):
    PsPlanFx, _ = fixed_structs()
    plan = PsPlanFx()
    params = abi.params_struct(PARAMS, "float")
    code = lib.ps_plan_fx_init(ctypes.byref(plan), ctypes.byref(params), cfg.step_s, cfg.theta)
    if code != abi.Status.PS_OK:
        raise RuntimeError(f"ps_plan_fx_init: {abi.status_name(code)}")
    return plan


def plan_fx_header(cfg: Config, build_dir: Path) -> Path:
    """fw_plan_fx.h: the plan of ps_plan_fx_init (host) as a const initializer."""
    plan = fixed_plan(host_library(cfg, build_dir), cfg)
    parts = []
    for name, ctype in type(plan)._fields_:
        value = getattr(plan, name)
        if ctype is ctypes.c_int32:
            parts.append(f"{int(value)}L")
        else:
            parts.append("{" + ", ".join(f"{int(v)}L" for v in value) + "}")
    path = build_dir / f"plan_fx_{key(cfg)}" / "fw_plan_fx.h"
    path.parent.mkdir(exist_ok=True)
    path.write_text("/* generated by scripts/bench_embedded.py from ps_plan_fx_init */\n"
                    "const ps_plan_fx fw_plan_fx = {\n    " + ",\n    ".join(parts) + "\n};\n")
    return path


def build_firmware(cfg: Config, build_dir: Path, stack_bytes: int = 0x400) -> Path:
    elf = build_dir / f"fw_{key(cfg, stack_bytes)}.elf"
    extra = []
    if cfg.plan_in_flash:
        extra = ["-I", str(plan_header(cfg, build_dir).parent)]
    if cfg.fixed:
        extra = ["-I", str(plan_fx_header(cfg, build_dir).parent)]
    cmd = [tool("gcc"), *ARM_FLAGS, *cfg.c_defines(), "-I", str(C_DIR), *extra,
           str(C_DIR / "spindle.c"), str(FW_DIR / "firmware.c"), "-T", str(FW_DIR / "m0plus.ld"),
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


# ---- ARMv6-M instruction rules ------------------------------------------------------------

def is_32bit(first: int) -> bool:
    return (first >> 11) in (0b11101, 0b11110, 0b11111)


def armv6m_violation(first: int, second: int | None) -> str | None:
    """None if the Thumb instruction exists on ARMv6-M, else why not."""
    if second is None:
        if (first & 0xF500) == 0xB100:
            return "cbz/cbnz"
        if (first & 0xFF00) == 0xBF00 and (first & 0x000F) != 0:
            return "it"
        return None
    if (first & 0xF800) == 0xF000 and (second & 0xD000) == 0xD000:
        return None  # bl
    if (first & 0xFFF0) == 0xF380 and (second & 0xFF00) == 0x8800:
        return None  # msr
    if first == 0xF3EF and (second & 0xF000) == 0x8000:
        return None  # mrs
    if first == 0xF3BF and (second & 0xFFF0) in (0x8F40, 0x8F50, 0x8F60):
        return None  # dsb, dmb, isb
    if (first & 0xFFF0) == 0xF7F0 and (second & 0xF000) == 0xA000:
        return None  # udf.w
    return f"32-bit {first:04x} {second:04x}"


def decode_block(code: bytes) -> tuple[int, list[str]]:
    """(instruction count, violations) of a straight run of Thumb code."""
    count, bad, i = 0, [], 0
    while i + 1 < len(code):
        first = code[i] | code[i + 1] << 8
        if is_32bit(first):
            second = code[i + 2] | code[i + 3] << 8
            i += 4
        else:
            second = None
            i += 2
        count += 1
        why = armv6m_violation(first, second)
        if why:
            bad.append(why)
    return count, bad


ARMV6M_32BIT = {"bl", "msr", "mrs", "dsb", "dmb", "isb", "udf.w"}
ARMV7M_ONLY_16BIT = {"cbz", "cbnz", "it", "ite", "itt", "itte", "ittt", "itee", "itet", "ittee"}


def objdump_violations(elf: Path) -> tuple[int, list[str]]:
    """Disassemble every code section; (instructions seen, ARMv7-M-only ones)."""
    raw = subprocess.run([tool("objdump"), "-d", str(elf)], check=True, capture_output=True,
                         text=True).stdout
    seen, bad = 0, []
    for line in raw.splitlines():
        parts = line.split("\t")
        if len(parts) < 3 or not parts[0].strip().endswith(":"):
            continue
        words = parts[1].split()
        mnemonic = parts[2].split()[0] if parts[2].split() else ""
        if mnemonic.startswith(".") or not words:
            continue  # data words in code
        seen += 1
        base = mnemonic.split(".")[0] if mnemonic != "udf.w" else mnemonic
        if len(words) == 2 and len(words[0]) == 4 and len(words[1]) == 4:
            if base not in ARMV6M_32BIT and mnemonic not in ARMV6M_32BIT:
                bad.append(line.strip())
        elif base in ARMV7M_ONLY_16BIT:
            bad.append(line.strip())
    return seen, bad


# ---- emulator -----------------------------------------------------------------------------

class M0Plus:
    """The firmware in unicorn's ARMv6-M (Cortex-M0) model, counting executed instructions."""

    def __init__(self, elf: Path):
        from unicorn import UC_ARCH_ARM, UC_HOOK_BLOCK, UC_MODE_THUMB, Uc
        from unicorn.arm_const import UC_CPU_ARM_CORTEX_M0

        self.uc = Uc(UC_ARCH_ARM, UC_MODE_THUMB)
        self.uc.ctl_set_cpu_model(UC_CPU_ARM_CORTEX_M0)
        self.model = self.uc.ctl_get_cpu_model()
        self.sym = symbols(elf)
        self.flash = (0x00000000, 64 * 1024)
        self.ram = (0x20000000, 8 * 1024)
        for base, size in (self.flash, self.ram):
            self.uc.mem_map(base, size)
        for vaddr, data in elf_load_segments(elf):
            self.uc.mem_write(vaddr, data)
        self.stack = (self.sym["_sstack"][0], self.sym["_estack"][0])
        self.uc.mem_write(self.stack[0], bytes([STACK_PATTERN]) * (self.stack[1] - self.stack[0]))
        self.count = 0
        self.blocks: dict[tuple[int, int], int] = {}
        self.violations: set[str] = set()
        functions = sorted((addr & ~1, name) for name, (addr, size) in self.sym.items()
                           if size > 0 and addr < self.flash[0] + self.flash[1])
        self._fn_addr = [a for a, _ in functions]
        self._fn_name = [n for _, n in functions]
        self.profile: collections.Counter = collections.Counter()
        self.uc.hook_add(UC_HOOK_BLOCK, self._on_block)

    def _on_block(self, uc, address, size, _user):
        key = (address, size)
        n = self.blocks.get(key)
        if n is None:
            n, bad = decode_block(bytes(uc.mem_read(address, size)))
            self.violations.update(f"{address:#x}: {b}" for b in bad)
            self.blocks[key] = n
        self.count += n
        self.profile[self._fn_name[bisect.bisect_right(self._fn_addr, address) - 1]] += n

    def call(self, name: str, *args: int) -> tuple[int, int]:
        """Run a firmware function to its return; (return value, instructions executed)."""
        from unicorn.arm_const import UC_ARM_REG_LR, UC_ARM_REG_R0, UC_ARM_REG_SP

        halt = self.sym["fw_halt"][0] & ~1
        for k, value in enumerate(args):
            self.uc.reg_write(UC_ARM_REG_R0 + k, value)
        self.uc.reg_write(UC_ARM_REG_SP, self.stack[1])
        self.uc.reg_write(UC_ARM_REG_LR, halt | 1)
        before = self.count
        self.uc.emu_start(self.sym[name][0] | 1, halt)
        return self.uc.reg_read(UC_ARM_REG_R0), self.count - before

    def stack_used(self) -> int:
        lo, hi = self.stack
        data = bytes(self.uc.mem_read(lo, hi - lo))
        untouched = len(data) - len(data.lstrip(bytes([STACK_PATTERN])))
        return hi - lo - untouched

    def write_io(self, L, gd, gs, fixed: bool = False) -> None:
        if fixed:  # Q24 lengths, Q8 drives (as fixed_rates rounds them)
            data = struct.pack("<6i", *(int(np.round(x * FX_Q24)) for x in L),
                               *(int(np.round(x * FX_DRIVE)) for x in (*gd, *gs)))
        else:
            data = struct.pack("<6f", *L, *gd, *gs)
        self.uc.mem_write(self.sym["io"][0], data)

    def read_rates(self, fixed: bool = False):
        raw = bytes(self.uc.mem_read(self.sym["io"][0] + 24, 24))
        if fixed:
            ia0, ia1, ii0, ii1 = (x / FX_RATE for x in struct.unpack("<4i", raw[:16]))
        else:
            ia0, ia1, ii0, ii1 = struct.unpack("<4f", raw[:16])
        st = struct.unpack("<2i", raw[16:])
        return (ia0, ia1), (ii0, ii1), st

    def read_symbol(self, name: str) -> bytes:
        addr, size = self.sym[name]
        return bytes(self.uc.mem_read(addr, size))


def elf_load_segments(elf: Path) -> list[tuple[int, bytes]]:
    """(address, bytes) of every PT_LOAD segment, at its run address (as after start-up)."""
    data = elf.read_bytes()
    e_phoff, = struct.unpack_from("<I", data, 0x1C)
    e_phentsize, e_phnum = struct.unpack_from("<HH", data, 0x2A)
    out = []
    for k in range(e_phnum):
        p_type, p_offset, p_vaddr, _paddr, p_filesz, _memsz = struct.unpack_from(
            "<6I", data, e_phoff + k * e_phentsize)
        if p_type == 1 and p_filesz:
            out.append((p_vaddr, data[p_offset:p_offset + p_filesz]))
    return out


def isa_probe() -> dict[str, str]:
    """What the emulator does with instructions an M0+ lacks (sdiv, add.w, cbz)."""
    from unicorn import UC_ARCH_ARM, UC_MODE_MCLASS, UC_MODE_THUMB, Uc, UcError
    from unicorn.arm_const import UC_ARM_REG_SP, UC_CPU_ARM_CORTEX_M0

    probes = {"sdiv r0, r0, r1": struct.pack("<HH", 0xFB90, 0xF0F1),
              "add.w r0, r0, r1": struct.pack("<HH", 0xEB00, 0x0001),
              "cbz r0, .+4": struct.pack("<H", 0xB100)}
    result = {}
    for mode_name, mode in (("thumb+M0 model", UC_MODE_THUMB),
                            ("mclass", UC_MODE_THUMB | UC_MODE_MCLASS)):
        for name, code in probes.items():
            uc = Uc(UC_ARCH_ARM, mode)
            uc.ctl_set_cpu_model(UC_CPU_ARM_CORTEX_M0)
            uc.mem_map(0, 0x10000)
            uc.mem_map(0x20000000, 0x1000)
            uc.reg_write(UC_ARM_REG_SP, 0x20001000)
            uc.mem_write(0x1000, code + b"\x00\xbf" * 4)
            try:
                uc.emu_start(0x1001, 0x1000 + len(code), count=1)
                outcome = "executed"
            except UcError as exc:
                outcome = f"faults ({exc})"
            result[f"{mode_name} (model {uc.ctl_get_cpu_model()}): {name}"] = outcome
    return result


# ---- protocol, reference, accuracy ------------------------------------------------------

def protocol(speed: float, step_s: float) -> np.ndarray:
    t = np.arange(round(DURATION_S / step_s) + 1) * step_s
    end = 1.0 + (1.08 - 0.95) / speed
    return 0.95 + speed * np.clip(t - 1.0, 0.0, end - 1.0)


def references(runs) -> dict[tuple, tuple[np.ndarray, np.ndarray]]:
    from spindle.reference import ramp_and_hold, solve_reference

    t = np.arange(round(DURATION_S / REFERENCE_DT_S) + 1) * REFERENCE_DT_S
    out = {}
    for run in runs:
        speed, gd, gs = run
        ref = solve_reference(ramp_and_hold(speed_L0_s=speed, gamma_dyn_pps=gd,
                                            gamma_stat_pps=gs), t, params=PARAMS)
        out[run] = (ref.ia, ref.ii)
    return out


def host_rates(lib, cfg: Config, run) -> tuple[np.ndarray, np.ndarray]:
    speed, gd, gs = run
    if cfg.fixed:
        L = protocol(speed, cfg.step_s)
        ia, ii, code = fixed_rates(lib, fixed_plan(lib, cfg), L, np.full(L.shape, gd),
                                   np.full(L.shape, gs))
        if code != abi.Status.PS_OK:
            raise RuntimeError(f"host fixed-point step: {abi.status_name(code)}")
        return ia, ii
    L = protocol(speed, cfg.step_s).astype(np.float32)
    _, PsSpindle = abi.structs("float")
    params = abi.params_struct(PARAMS, "float")
    s = PsSpindle()
    code = lib.ps_spindle_init(ctypes.byref(s), ctypes.byref(params), L[0], gd, gs)
    if code != abi.Status.PS_OK:
        raise RuntimeError("init failed")
    ia = np.empty(len(L))
    ii = np.empty(len(L))
    a, b = ctypes.c_float(), ctypes.c_float()
    lib.ps_spindle_afferents(ctypes.byref(s), ctypes.byref(params), ctypes.byref(a),
                             ctypes.byref(b))
    ia[0], ii[0] = a.value, b.value
    if cfg.plan:
        plan = abi.plan_struct("float")()
        lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(params), cfg.step_s, cfg.theta)
    for j in range(1, len(L)):
        if cfg.plan:
            code = lib.ps_spindle_step_plan(ctypes.byref(s), ctypes.byref(plan), L[j], gd, gs,
                                            ctypes.byref(a), ctypes.byref(b))
        else:
            code = lib.ps_spindle_step(ctypes.byref(s), ctypes.byref(params), L[j], gd, gs,
                                       cfg.step_s, cfg.theta, ctypes.byref(a), ctypes.byref(b))
        if code != abi.Status.PS_OK:
            raise RuntimeError(f"host step {j}: {abi.status_name(code)}")
        ia[j], ii[j] = a.value, b.value
    return ia, ii


def accuracy(lib, cfg: Config, refs) -> float:
    """Worst-run RMS (pps) of Ia and II against the reference, over the 9 runs."""
    every = round(cfg.step_s / REFERENCE_DT_S)
    worst = 0.0
    for run, (ref_ia, ref_ii) in refs.items():
        ia, ii = host_rates(lib, cfg, run)
        for got, ref in ((ia, ref_ia[::every]), (ii, ref_ii[::every])):
            worst = max(worst, float(np.sqrt(np.mean((got - ref) ** 2))))
    return worst


# ---- one configuration --------------------------------------------------------------------

@dataclasses.dataclass
class Measured:
    cfg: Config
    instr_mean: float
    instr_max: int
    mips: float
    rms_pps: float
    flash: int
    ram: int
    stack_used: int
    max_diff_host_pps: float
    steps: int
    violations: list[str]
    profile: list[tuple[str, int]]


def measure(cfg: Config, runs, refs, build_dir: Path) -> Measured:
    lib = host_library(cfg, build_dir)
    rms = accuracy(lib, cfg, refs)
    elf = build_firmware(cfg, build_dir)
    emu = M0Plus(elf)
    # (the fixed-point firmware holds only the plan, made from PARAMS by plan_fx_header)
    if not cfg.fixed and emu.read_symbol("fw_params") != bytes(
            abi.params_struct(PARAMS, "float")):
        raise RuntimeError("fw_params in firmware.c differ from spindle.HUMAN")
    counts = []
    max_diff = 0.0
    # the runs in pairs: muscle 0 and muscle 1 follow different runs at once
    pairs = [runs[k:k + 2] for k in range(0, len(runs), 2)]
    for pair in pairs:
        pair = list(pair) + [pair[0]] * (2 - len(pair))
        lengths = [protocol(speed, cfg.step_s) for speed, _, _ in pair]
        gds = [gd for _, gd, _ in pair]
        gss = [gs for _, _, gs in pair]
        emu.write_io([x[0] for x in lengths], gds, gss, cfg.fixed)
        status, _ = emu.call("fw_init")
        if status != abi.Status.PS_OK:
            raise RuntimeError(f"fw_init: {abi.status_name(status)}")
        host = [host_rates(lib, cfg, run) for run in pair]
        for j in range(1, len(lengths[0])):
            emu.write_io([x[j] for x in lengths], gds, gss, cfg.fixed)
            for k in range(2):
                status, n = emu.call("fw_step_muscle", k)
                if status != abi.Status.PS_OK:
                    raise RuntimeError(f"fw_step_muscle: {abi.status_name(status)}")
                counts.append(n)
            ia, ii, _ = emu.read_rates(cfg.fixed)
            for k in range(2):
                max_diff = max(max_diff, abs(ia[k] - host[k][0][j]), abs(ii[k] - host[k][1][j]))
    # RAM: re-link with the stack reservation cut to the measured high-water mark plus a
    # 64-byte margin (rounded to 64 B); arm-none-eabi-size then counts it in bss.
    stack = (emu.stack_used() + 64 + 63) // 64 * 64
    sized = build_firmware(cfg, build_dir, stack_bytes=stack)
    flash, ram = sizes(sized)
    seen, bad = objdump_violations(sized)
    if seen < 100:
        raise RuntimeError("objdump parsing found almost no instructions")
    counts = np.array(counts)
    return Measured(cfg, float(counts.mean()), int(counts.max()),
                    float(counts.mean()) / cfg.step_s / 1e6, rms, flash, ram, emu.stack_used(),
                    max_diff, len(counts), sorted(emu.violations) + bad,
                    [(name, n // len(counts)) for name, n in emu.profile.most_common(12)])


# ---- demo motion: drives that change every sample -----------------------------------------

DEMO_LOW_DEG, DEMO_HIGH_DEG, DEMO_SPEED_DEG_S = 20.0, 110.0, 130.0
DEMO_CYCLES = 4


@dataclasses.dataclass
class DemoMeasured:
    steps: int
    instr_mean: tuple[float, float]  # per muscle (BRA, TRImed)
    instr_max: int
    held_instr_mean: float  # the same lengths, the drives held at their first sample
    held_instr_max: int
    peak_t_s: float  # time of the costliest step
    rms_vs_double: dict[str, float]  # "BRA Ia" ... (pps): against double ps_spindle_step
    rms_vs_chain: dict[str, float]  # against the numpy chain's own rates (1 ms trapezoidal)
    max_diff_host_pps: float
    drive_changes: tuple[float, float]  # fraction of steps in which gs, gd change

    def mips(self, step_s: float) -> float:
        return float(np.mean(self.instr_mean)) / step_s / 1e6


def demo_inputs(step_s: float):
    """The seed paper's repeated rapid flexion-extension through the numpy chain, sampled once
    per spindle step: (trace, lengths (T, 2) L0, gd (T, 2), gs (T, 2) pps)."""
    from proprio_env.servo_motion import triangle_deg
    from spindle.chain import ChainConfig, run_chain

    period_s = 2 * (DEMO_HIGH_DEG - DEMO_LOW_DEG) / DEMO_SPEED_DEG_S
    t = np.arange(round(DEMO_CYCLES * period_s / step_s) + 1) * step_s
    angle = triangle_deg(t, DEMO_LOW_DEG, DEMO_HIGH_DEG, DEMO_SPEED_DEG_S)
    trace = run_chain(t, angle_deg=angle, config=ChainConfig(params=PARAMS))
    if not trace.accepted.all():
        raise RuntimeError(f"the chain rejected demo samples: {trace.counters}")
    return trace, trace.length_L0, trace.gamma_dynamic_pps, trace.gamma_static_pps


def emulate_demo(emu: M0Plus, L: np.ndarray, gd: np.ndarray, gs: np.ndarray):
    """Both muscles through the sequence in the firmware: (instructions (T-1, 2), Ia, II)."""
    emu.write_io(L[0], gd[0], gs[0], True)
    status, _ = emu.call("fw_init")
    if status != abi.Status.PS_OK:
        raise RuntimeError(f"fw_init: {abi.status_name(status)}")
    counts = np.empty((len(L) - 1, 2), dtype=np.int64)
    ia = np.empty((len(L) - 1, 2))
    ii = np.empty((len(L) - 1, 2))
    for j in range(1, len(L)):
        emu.write_io(L[j], gd[j], gs[j], True)
        for k in range(2):
            status, counts[j - 1, k] = emu.call("fw_step_muscle", k)
            if status != abi.Status.PS_OK:
                raise RuntimeError(f"fw_step_muscle({k}) at step {j}: "
                                   f"{abi.status_name(status)}")
        ia[j - 1], ii[j - 1], _ = emu.read_rates(True)
    return counts, ia, ii


def measure_demo(cfg: Config, build_dir: Path) -> DemoMeasured:
    """The fixed-point firmware on the demo motion, drives changing as the chain makes them."""
    from spindle.chain import MUSCLES

    if not cfg.fixed:
        raise ValueError("the demo motion is measured on the fixed-point configuration")
    trace, L, gd, gs = demo_inputs(cfg.step_s)
    lib = host_library(cfg, build_dir)
    plan = fixed_plan(lib, cfg)
    emu = M0Plus(build_firmware(cfg, build_dir))
    counts, emu_ia, emu_ii = emulate_demo(emu, L, gd, gs)
    held, _, _ = emulate_demo(emu, L, np.broadcast_to(gd[0], gd.shape),
                              np.broadcast_to(gs[0], gs.shape))
    rms_double, rms_chain, max_diff = {}, {}, 0.0
    for k, muscle in enumerate(MUSCLES):
        fx_ia, fx_ii, code = fixed_rates(lib, plan, L[:, k], gd[:, k], gs[:, k])
        if code != abi.Status.PS_OK:
            raise RuntimeError(f"host fixed-point step ({muscle}): {abi.status_name(code)}")
        max_diff = max(max_diff, float(np.max(np.abs(emu_ia[:, k] - fx_ia[1:]))),
                       float(np.max(np.abs(emu_ii[:, k] - fx_ii[1:]))))
        ref_ia, ref_ii = native_spindle.run_spindle(L[:, k], gd[:, k], gs[:, k], cfg.step_s,
                                              cfg.theta, 1, PARAMS, "double")
        for name, got, ref, chain in (("Ia", fx_ia, ref_ia, trace.ia_pps[:, k]),
                                      ("II", fx_ii, ref_ii, trace.ii_pps[:, k])):
            rms_double[f"{muscle} {name}"] = float(np.sqrt(np.mean((got - ref) ** 2)))
            rms_chain[f"{muscle} {name}"] = float(np.sqrt(np.mean((got - chain) ** 2)))
    changes = (float(np.mean(np.diff(gs, axis=0) != 0)), float(np.mean(np.diff(gd, axis=0) != 0)))
    return DemoMeasured(len(counts), (float(counts[:, 0].mean()), float(counts[:, 1].mean())),
                        int(counts.max()), float(held.mean()), int(held.max()),
                        float(trace.t_s[1 + int(np.argmax(counts.max(axis=1)))]), rms_double,
                        rms_chain, max_diff, changes)


def print_demo(d: DemoMeasured, cfg: Config) -> None:
    step_s = cfg.step_s

    def worst(rms: dict[str, float]) -> str:
        return ", ".join(f"{k} {v:.2g}" for k, v in rms.items())

    print(f"\ndemo motion ({cfg.label}): triangle {DEMO_LOW_DEG:g}-{DEMO_HIGH_DEG:g} deg at "
          f"{DEMO_SPEED_DEG_S:g} deg/s, {DEMO_CYCLES} cycles, numpy chain (ChainConfig()) "
          f"sampled every {step_s * 1e3:g} ms, BRA and TRImed lengths and the chain's own "
          f"gamma_s, gamma_d per step (gamma_s changes in {d.drive_changes[0]:.0%} of the "
          f"steps, gamma_d in {d.drive_changes[1]:.0%}); {d.steps} steps x 2 muscles emulated")
    print("| input | instr/step BRA | instr/step TRImed | MIPS/muscle | peak instr/step "
          "| peak MIPS |")
    print("|---|---:|---:|---:|---:|---:|")
    print(f"| demo motion, drives from the chain | {d.instr_mean[0]:.0f} | {d.instr_mean[1]:.0f} "
          f"| {d.mips(step_s):.3f} | {d.instr_max} | {d.instr_max / step_s / 1e6:.3f} |")
    print(f"| same lengths, drives held at the first sample | | | "
          f"{d.held_instr_mean / step_s / 1e6:.3f} | {d.held_instr_max} "
          f"| {d.held_instr_max / step_s / 1e6:.3f} |")
    print(f"  costliest step at t = {d.peak_t_s:.3f} s")
    print(f"  fixed point vs double ps_spindle_step ({step_s * 1e3:g} ms, same inputs), RMS pps: "
          f"{worst(d.rms_vs_double)}")
    print(f"  fixed point vs the numpy chain's own rates (trapezoidal 1 ms), RMS pps: "
          f"{worst(d.rms_vs_chain)}")
    print(f"  emulator vs host fixed-point build: max {d.max_diff_host_pps:.2g} pps")
    print(f"demo_mips_per_muscle={d.mips(step_s):.4f} "
          f"demo_peak_mips={d.instr_max / step_s / 1e6:.4f} "
          f"demo_rms_vs_double_pps={max(d.rms_vs_double.values()):.4f}")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="only the final configuration, emulated on 2 of the 9 runs")
    ap.add_argument("--build-dir", type=Path, default=None)
    ap.add_argument("--profile", action="store_true",
                    help="print the instructions per step spent in each function")
    ap.add_argument("--only", type=int, nargs="*", default=None,
                    help="indices of the lever rows to measure")
    ap.add_argument("--no-demo", action="store_true",
                    help="skip the demo motion (the fixed-point step with moving drives)")
    args = ap.parse_args(argv)
    try:
        import unicorn
    except ImportError:
        sys.exit("needs unicorn >= 2.1: pip install 'unicorn>=2.1'")
    t0 = time.perf_counter()
    all_runs = [(v, gd, gs) for v in SPEEDS for gd, gs in DRIVES]
    build_dir = args.build_dir or Path(tempfile.mkdtemp(prefix="bench_embedded_"))
    build_dir.mkdir(parents=True, exist_ok=True)
    print(f"unicorn {unicorn.__version__}; instruction-set probe:")
    for what, outcome in isa_probe().items():
        print(f"  {what}: {outcome}")
    refs = references(all_runs)
    print(f"reference (scipy Radau, HUMAN, 9 runs): {time.perf_counter() - t0:.0f} s")
    configs = [FINAL] if args.quick else LEVERS
    if args.only is not None:
        configs = [LEVERS[k] for k in args.only]
    rows = []
    for cfg in configs:
        # lever rows: instructions over 2 runs (the fastest ramp with dynamic drive, the
        # medium one with static drive); the final row in full mode: all 9 runs
        emulated = all_runs if (cfg is FINAL and not args.quick) else list(QUICK_RUNS)
        m = measure(cfg, emulated, refs, build_dir)
        rows.append(m)
        print(f"{cfg.label}: {m.instr_mean:.0f} instr/step (max {m.instr_max}), "
              f"{m.mips:.3f} MIPS/muscle, rms {m.rms_pps:.3f} pps, flash {m.flash} B, "
              f"RAM {m.ram} B (stack high-water {m.stack_used} B), emulator vs host "
              f"{m.max_diff_host_pps:.2g} pps over {m.steps} steps", flush=True)
        if args.profile:
            print("  instructions per step by function:",
                  ", ".join(f"{name} {n}" for name, n in m.profile))
        if m.violations:
            print("  ARMv7-M-only instructions:", *m.violations[:10], sep="\n    ")
            return 1
    print("\n| configuration | step (ms) | instr/step | MIPS/muscle | RMS (pps) | flash (B) "
          "| RAM (B) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for m in rows:
        print(f"| {m.cfg.label} | {m.cfg.step_s * 1e3:g} | {m.instr_mean:.0f} | {m.mips:.3f} | "
              f"{m.rms_pps:.3f} | {m.flash} | {m.ram} |")
    # the last line: the cheapest measured configuration within the accuracy target
    within = [m for m in rows if m.rms_pps <= RMS_TARGET_PPS]
    final = min(within, key=lambda m: m.mips) if within else rows[-1]
    if not args.no_demo:
        demo = measure_demo(FINAL, build_dir)
        print_demo(demo, FINAL)
        if demo.max_diff_host_pps != 0.0:
            print("  the emulated fixed-point rates differ from the host build's")
            return 1
    print(f"best within {RMS_TARGET_PPS} pps RMS: {final.cfg.label}")
    print(f"ARMv6-M check: every executed instruction decoded, objdump of the whole firmware: "
          f"no ARMv7-M-only instruction; total {time.perf_counter() - t0:.0f} s")
    print(f"m0plus_mips_per_muscle={final.mips:.4f} rms_pps={final.rms_pps:.4f} "
          f"flash_bytes={final.flash} ram_bytes={final.ram}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
