"""The Cortex-M0+ cycle model (spindle.native.m0plus.cycles) against the cycle counts of the
ARM Cortex-M0+ Technical Reference Manual (ARM DDI 0484C, Table 3-1; single-cycle
multiplier, zero wait states), the EFM32ZG clock bands and the power formula."""

from __future__ import annotations

import struct

import pytest

from spindle.native.m0plus import cycles

# (encoding, cycles from the TRM table, whether a conditional branch)
TRM = [
    ((0x2001,), 1, False),          # movs r0, #1
    ((0x4348,), 1, False),          # muls r0, r1, r0: single-cycle multiplier
    ((0x4408,), 1, False),          # add r0, r1 (high-register form, not to PC)
    ((0x458F,), 1, False),          # cmp pc, r1: a compare, not a write to PC
    ((0x6808,), 2, False),          # ldr r0, [r1]
    ((0x6008,), 2, False),          # str r0, [r1]
    ((0x4801,), 2, False),          # ldr r0, [pc, #4]
    ((0x5C08,), 2, False),          # ldrb r0, [r1, r0]
    ((0x9001,), 2, False),          # str r0, [sp, #4]
    ((0x8808,), 2, False),          # ldrh r0, [r1]
    ((0xC806,), 3, False),          # ldmia r0!, {r1, r2}: 1 + N
    ((0xB5F0,), 6, False),          # push {r4-r7, lr}: 1 + N
    ((0xBC10,), 2, False),          # pop {r4}: 1 + N
    ((0xBDF0,), 7, False),          # pop {r4-r7, pc}: 3 + N
    ((0xD001,), 1, True),           # beq (not taken; taken adds 1)
    ((0xE7FE,), 2, False),          # b
    ((0x4770,), 2, False),          # bx lr
    ((0x4788,), 2, False),          # blx r1
    ((0x468F,), 2, False),          # mov pc, r1
    ((0xF000, 0xF800), 3, False),   # bl
]


@pytest.mark.parametrize(("halfwords", "expected", "cond"), TRM)
def test_instruction_cycles_follow_the_trm_table(halfwords, expected, cond):
    first, second = halfwords[0], (halfwords[1] if len(halfwords) > 1 else None)
    n, kind = cycles.instruction_cycles(first, second)
    assert n == expected
    assert (kind == "cond") == cond


def test_block_cycles_sum_and_flag_a_final_conditional_branch():
    code = struct.pack("<5H", 0xB5F0, 0x6808, 0x4348, 0xF000, 0xF800)  # push, ldr, muls, bl
    assert cycles.block_cycles(code) == (6 + 2 + 1 + 3, False)
    assert cycles.block_cycles(struct.pack("<2H", 0x2001, 0xD001)) == (2, True)


def test_clock_choice_and_power():
    # 20,000 cycles in 75 % of 2 ms need 13.3 MHz: the 14 MHz band (0 wait states)
    assert cycles.lowest_clock_mhz(20_000, 30_000, 2e-3) == 14.0
    # above 16 MHz the 1-wait-state count applies: 30,000 at 0 WS but 40,000 at 1 WS fit
    # 24 MHz (1.67 ms > 1.5 ms: no), so no band keeps the margin
    assert cycles.lowest_clock_mhz(30_000, 40_000, 2e-3) is None
    assert cycles.lowest_clock_mhz(30_000, 40_000, 2e-3, margin=0.0) == 21.0
    assert cycles.needed_clock_mhz(36_000, 2e-3) == pytest.approx(24.0)
    assert cycles.active_power_mw(24.0) == pytest.approx(3.0 * 114e-6 * 24 * 1e3)  # 8.208 mW
    assert cycles.wait_states(16.0) == 0 and cycles.wait_states(21.0) == 1
