"""The firmware in unicorn's ARMv6-M (Cortex-M0) model, counting executed instructions.

Every executed block is decoded once with the ARMv6-M rules (:mod:`.isa`) and counted each
time it runs; the count is also attributed to the function it lies in (``profile``). With
``cycles=True`` it also counts Cortex-M0+ cycles (:mod:`.cycles`: the block's instruction
timings, one more for a taken conditional branch, seen as a next block that does not follow
on), the 32-bit words fetched from flash and the data reads from flash (for the wait-state
model), and attributes all of them to the stage being run: ``stages`` maps function names to
stage names, and a stage runs from the entry of its function to the entry of the next one.
"""

from __future__ import annotations

import bisect
import collections
import struct
from pathlib import Path

import numpy as np

from spindle.native.fixed import FX_DRIVE, FX_Q24, FX_RATE
from spindle.native.m0plus.build import symbols
from spindle.native.m0plus.cycles import block_cycles
from spindle.native.m0plus.isa import decode_block

STACK_PATTERN = 0xA5
"""Written over the stack before the first call; what is left of it gives the high-water."""
FLASH = (0x00000000, 64 * 1024)
RAM = (0x20000000, 8 * 1024)


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


class M0Plus:
    """The firmware in unicorn's ARMv6-M (Cortex-M0) model, counting executed instructions."""

    def __init__(self, elf: Path, cycles: bool = False, stages: dict[str, str] | None = None):
        from unicorn import UC_ARCH_ARM, UC_HOOK_BLOCK, UC_HOOK_MEM_READ, UC_MODE_THUMB, Uc
        from unicorn.arm_const import UC_CPU_ARM_CORTEX_M0

        self.uc = Uc(UC_ARCH_ARM, UC_MODE_THUMB)
        self.uc.ctl_set_cpu_model(UC_CPU_ARM_CORTEX_M0)
        self.model = self.uc.ctl_get_cpu_model()
        self.sym = symbols(elf)
        self.flash, self.ram = FLASH, RAM
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
        # cycle model: totals, and per stage [instructions, cycles, fetch words, flash reads]
        self.cycles = self.fetches = self.flash_reads = 0
        self.stage = "entry"
        self.by_stage: dict[str, list[int]] = collections.defaultdict(lambda: [0, 0, 0, 0])
        self._stage_at = {self.sym[f][0] & ~1: name for f, name in (stages or {}).items()
                          if f in self.sym}
        self._timing: dict[tuple[int, int], tuple[int, bool, int]] = {}
        self._pending_cond_end = -1
        if cycles:
            self.uc.hook_add(UC_HOOK_BLOCK, self._on_block_cycles)
            self.uc.hook_add(UC_HOOK_MEM_READ, self._on_flash_read, begin=self.flash[0],
                             end=self.flash[0] + self.flash[1] - 1)
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

    def _on_block_cycles(self, uc, address, size, _user):
        timing = self._timing.get((address, size))
        if timing is None:
            cycles, cond = block_cycles(bytes(uc.mem_read(address, size)))
            words = (address + size - 1) // 4 - address // 4 + 1
            timing = self._timing[(address, size)] = (cycles, cond, words)
        cycles, cond, words = timing
        if self._pending_cond_end >= 0 and address != self._pending_cond_end:
            cycles += 1  # the previous block's conditional branch was taken
        self._pending_cond_end = address + size if cond else -1
        self.stage = self._stage_at.get(address, self.stage)
        self.cycles += cycles
        self.fetches += words
        row = self.by_stage[self.stage]
        row[1] += cycles
        row[2] += words
        row[0] += self.blocks.get((address, size)) or decode_block(
            bytes(uc.mem_read(address, size)))[0]

    def _on_flash_read(self, _uc, _access, _address, _size, _value, _user):
        self.flash_reads += 1
        self.by_stage[self.stage][3] += 1

    def call(self, name: str, *args: int) -> tuple[int, int]:
        """Run a firmware function to its return; (return value, instructions executed)."""
        from unicorn.arm_const import UC_ARM_REG_LR, UC_ARM_REG_R0, UC_ARM_REG_SP

        halt = self.sym["fw_halt"][0] & ~1
        for k, value in enumerate(args):
            self.uc.reg_write(UC_ARM_REG_R0 + k, value)
        self.uc.reg_write(UC_ARM_REG_SP, self.stack[1])
        self.uc.reg_write(UC_ARM_REG_LR, halt | 1)
        before = self.count
        self.stage = "entry"
        self._pending_cond_end = -1
        self.uc.emu_start(self.sym[name][0] | 1, halt)
        return self.uc.reg_read(UC_ARM_REG_R0), self.count - before

    def stack_used(self) -> int:
        """The stack's high-water mark (bytes) over every call so far."""
        lo, hi = self.stack
        data = bytes(self.uc.mem_read(lo, hi - lo))
        untouched = len(data) - len(data.lstrip(bytes([STACK_PATTERN])))
        return hi - lo - untouched

    def write_io(self, L, gd, gs, fixed: bool = False) -> None:
        """One sample of both muscles into the mailbox ``io`` (float32, or the Q formats)."""
        if fixed:  # Q24 lengths, Q8 drives (as spindle.native.fixed rounds them)
            data = struct.pack("<6i", *(int(np.round(x * FX_Q24)) for x in L),
                               *(int(np.round(x * FX_DRIVE)) for x in (*gd, *gs)))
        else:
            data = struct.pack("<6f", *L, *gd, *gs)
        self.uc.mem_write(self.sym["io"][0], data)

    def read_rates(self, fixed: bool = False):
        """((Ia0, Ia1), (II0, II1), (status0, status1)) from the mailbox, rates in pps."""
        raw = bytes(self.uc.mem_read(self.sym["io"][0] + 24, 24))
        if fixed:
            ia0, ia1, ii0, ii1 = (x / FX_RATE for x in struct.unpack("<4i", raw[:16]))
        else:
            ia0, ia1, ii0, ii1 = struct.unpack("<4f", raw[:16])
        st = struct.unpack("<2i", raw[16:])
        return (ia0, ia1), (ii0, ii1), st

    def read_symbol(self, name: str) -> bytes:
        """The bytes of a firmware object."""
        addr, size = self.sym[name]
        return bytes(self.uc.mem_read(addr, size))
