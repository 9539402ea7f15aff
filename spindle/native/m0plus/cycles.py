"""Cortex-M0+ cycle counts of executed code, and the clock and power they imply.

Cycles per instruction, zero wait states (ARM Cortex-M0+ Technical Reference Manual, ARM DDI
0484C, Table 3-1 "Cortex-M0+ instruction summary"; the same table is reproduced in NXP's
LPC800 user manual UM10601, "Cortex-M0+ instruction summary"), for a core built with the
single-cycle multiplier (the EFM32 Zero Gecko's):

| instructions | cycles |
|---|---:|
| data processing, MULS (single-cycle multiplier), compare, shifts, extend, ADR, NOP | 1 |
| LDR*, STR* (any addressing mode, literal loads included) | 2 |
| LDM, STM, PUSH (N registers) | 1 + N |
| POP (N registers) / POP with PC (N low registers) | 1 + N / 3 + N |
| B<cond> not taken / taken | 1 / 2 |
| B, BX, BLX, MOV PC / ADD PC | 2 |
| BL (32-bit) | 3 |
| MRS, MSR, DMB, DSB, ISB (not on the measured path) | 3 / 3 / 3 / 3 / 3 |

Flash wait states: the EFM32 Zero Gecko runs from flash with 0 wait states up to 16 MHz and
needs 1 above (reference manual EFM32ZG-RM, MSC_READCTRL MODE WS0 / WS1); the model adds one
cycle per wait state for every 32-bit word fetched from flash (the M0+ fetches 32 bits, two
16-bit instructions, per access; a taken branch refetches) and for every data read from
flash (literal pools, const tables), which over-counts wherever the pipeline hides a fetch
(an upper bound).

Power: the EFM32ZG datasheet (EFM32ZG222 / EFM32ZG108 family data sheets, "Current
consumption", EM0 running prime-number code from flash) gives 114 uA/MHz at 3 V and 24 MHz
(HFXO); the active power at a clock f is taken as 3 V x 114 uA/MHz x f (the datasheet's
figures rise slightly towards lower clocks, e.g. ~130 uA/MHz near 1 MHz, so the figure at low
clocks is an estimate within ~15 %).
"""

from __future__ import annotations

import math

ACTIVE_UA_PER_MHZ = 114.0
"""EFM32ZG datasheet: EM0 current from flash at 24 MHz, 3 V (uA/MHz)."""
SUPPLY_V = 3.0
"""The datasheet's supply for that figure (V)."""
HFRCO_BANDS_MHZ = (1.0, 7.0, 11.0, 14.0, 21.0, 24.0)
"""The EFM32ZG's high-frequency RC oscillator bands (MHz): the clocks a design picks from."""
MAX_CLOCK_MHZ = 24.0
WAIT_STATE_ABOVE_MHZ = 16.0
"""Flash needs one wait state above this clock (MSC_READCTRL WS1)."""
DEADLINE_MARGIN = 0.25
"""Headroom kept below the deadline: the worst sample may use 75 % of its period."""


def instruction_cycles(first: int, second: int | None) -> tuple[int, str]:
    """(cycles at zero wait states, kind) of one Thumb instruction; kind is "cond" for a
    conditional branch (one more cycle when taken), else "".
    """
    if second is not None:
        if (first & 0xF800) == 0xF000 and (second & 0xD000) == 0xD000:
            return 3, ""  # BL
        return 3, ""  # MRS, MSR, barriers
    top5, top4 = first >> 11, first >> 12
    if top4 == 0b1101 and ((first >> 8) & 0xF) < 0b1110:
        return 1, "cond"
    if top5 == 0b11100:
        return 2, ""  # B
    if (first & 0xFF00) == 0x4700:
        return 2, ""  # BX, BLX
    if (first & 0xFC00) == 0x4400 and (first & 0x0087) == 0x0087 and (first & 0x0300) != 0x0100:
        return 2, ""  # ADD / MOV with PC as destination
    if top5 == 0b01001 or top4 in (0b0101, 0b0110, 0b0111, 0b1000, 0b1001):
        return 2, ""  # LDR / STR: literal, register offset, immediate, halfword, SP-relative
    if top4 == 0b1100:  # LDM / STM
        return 1 + bin(first & 0xFF).count("1"), ""
    if (first & 0xFE00) == 0xB400:  # PUSH {..., LR}
        return 1 + bin(first & 0x1FF).count("1"), ""
    if (first & 0xFE00) == 0xBC00:  # POP {..., PC}
        n = bin(first & 0xFF).count("1")
        return (3 + n, "") if first & 0x100 else (1 + n, "")
    return 1, ""


def block_cycles(code: bytes) -> tuple[int, bool]:
    """(cycles at zero wait states with a final conditional branch not taken, whether the
    block ends in a conditional branch) of a straight run of Thumb code."""
    cycles, i, kind = 0, 0, ""
    while i + 1 < len(code):
        first = code[i] | code[i + 1] << 8
        if (first >> 11) in (0b11101, 0b11110, 0b11111):
            second = code[i + 2] | code[i + 3] << 8
            i += 4
        else:
            second = None
            i += 2
        n, kind = instruction_cycles(first, second)
        cycles += n
    return cycles, kind == "cond"


def wait_states(clock_mhz: float) -> int:
    """Flash wait states of the EFM32ZG at a clock."""
    return 0 if clock_mhz <= WAIT_STATE_ABOVE_MHZ else 1


def lowest_clock_mhz(peak_cycles_ws0: int, peak_cycles_ws1: int, deadline_s: float,
                     margin: float = DEADLINE_MARGIN) -> float | None:
    """The lowest HFRCO band at which the costliest sample (cycles at 0 and 1 wait states)
    takes at most (1 - margin) of its deadline; None if no band of the part does."""
    for f in HFRCO_BANDS_MHZ:
        cycles = peak_cycles_ws0 if wait_states(f) == 0 else peak_cycles_ws1
        if cycles / (f * 1e6) <= (1.0 - margin) * deadline_s:
            return f
    return None


def needed_clock_mhz(peak_cycles: int, deadline_s: float,
                     margin: float = DEADLINE_MARGIN) -> float:
    """The clock at which ``peak_cycles`` take exactly (1 - margin) of the deadline."""
    return peak_cycles / ((1.0 - margin) * deadline_s) / 1e6


def active_power_mw(clock_mhz: float) -> float:
    """EM0 power at a clock from the datasheet's uA/MHz and supply (mW)."""
    return SUPPLY_V * ACTIVE_UA_PER_MHZ * clock_mhz * 1e-3


def duty_power_mw(clock_mhz: float, busy_fraction: float, sleep_ua: float = 1.0) -> float:
    """Average power when the core runs ``busy_fraction`` of the time and sleeps (EM1/EM2,
    ``sleep_ua``) otherwise; not the headline figure (it depends on the sleep mode)."""
    if not 0.0 <= busy_fraction <= 1.0 or not math.isfinite(busy_fraction):
        raise ValueError(f"busy_fraction={busy_fraction!r} must lie in [0, 1]")
    return SUPPLY_V * (ACTIVE_UA_PER_MHZ * clock_mhz * busy_fraction
                       + sleep_ua * (1 - busy_fraction)) * 1e-3
