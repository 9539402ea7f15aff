"""The C spindle on a Cortex-M0+: cross-build, instruction-set check, emulation, measurement.

The firmware it measures is C (``spindle/native/c/m0plus/``: ``firmware.c``, ``m0plus.ld``);
this package is the host side that ``scripts/bench_embedded.py`` drives:

- :mod:`.build`: the firmware for ``-mcpu=cortex-m0plus`` (soft float, newlib-nano) and its
  float32 host twin, the plans compiled in as const initializers, sizes and symbols;
- :mod:`.isa`: the ARMv6-M rules (every executed instruction, and an objdump of the whole
  firmware) and what the emulator does with instructions an M0+ lacks;
- :mod:`.emulator`: the firmware in unicorn's Cortex-M0 model, counting instructions;
- :mod:`.measure`: the Mileusnic Fig. 3 protocol, the lever table, accuracy against the stiff
  reference, and the demo motion (drives that change every sample);
- :mod:`.cycles`: Cortex-M0+ cycles per instruction (ARM DDI 0484C), the EFM32ZG's flash wait
  states, clock bands and active power;
- :mod:`.system_config`, :mod:`.system`: the whole-system firmware (``system.c``: the chain,
  the fixed-point spindles and the pulse encoder per encoder sample), its configuration
  generated from a ChainConfig, and its comparison with the host double chain.

The start-up code both firmwares share is ``c/m0plus/startup.c``.

Needs the ``embedded`` extra (unicorn) and Debian's ``gcc-arm-none-eabi
libnewlib-arm-none-eabi``; nothing else in ``spindle`` imports it.
"""
