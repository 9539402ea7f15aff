"""The ARMv6-M instruction-set check: what a Cortex-M0+ can execute.

unicorn opened in M-class mode silently models a Cortex-M33 (its CPU model cannot be changed
there, and sdiv runs). The emulator is therefore opened in Thumb mode with the Cortex-M0
model (ARMv6-M), and :func:`isa_probe` shows that sdiv and a Thumb-2 32-bit data-processing
instruction do fault. That model still executes cbz/cbnz and it (ARMv7-M only), so every
executed instruction is also decoded with the ARMv6-M encoding rules (:func:`decode_block`),
and the whole binary is disassembled with arm-none-eabi-objdump and checked the same way
(:func:`objdump_violations`); any ARMv7-M-only instruction is an error.
"""

from __future__ import annotations

import struct
import subprocess
from pathlib import Path

from spindle.native.m0plus.build import tool

ARMV6M_32BIT = {"bl", "msr", "mrs", "dsb", "dmb", "isb", "udf.w"}
ARMV7M_ONLY_16BIT = {"cbz", "cbnz", "it", "ite", "itt", "itte", "ittt", "itee", "itet", "ittee"}


def is_32bit(first: int) -> bool:
    """Whether the Thumb halfword ``first`` opens a 32-bit instruction."""
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
