"""The C port (``c/``: ``proprio.h``, ``spindle.c``, ``chain.c``, the Cortex-M0+ firmware and
the fuzz drivers) and its one Python binding layer.

- :mod:`spindle.native.build`: compile the library on first use, cache and verify it;
- :mod:`spindle.native.abi`: the header as Python sees it (status codes, struct mirrors);
- :mod:`spindle.native.spindle`: the C spindle, ``spindle.simulate(..., backend="c")``;
- :mod:`spindle.native.chain`: the C arm chain (:class:`~spindle.native.chain.CArmChain`)
  and the device configuration as C source (``python -m spindle.native.chain``);
- :mod:`spindle.native.fixed`: the fixed-point step (int32 Q24) of the FPU-less target;
- :mod:`spindle.native.m0plus`: the Cortex-M0+ bench (cross-build, instruction-set check,
  emulator, measurement) that ``scripts/bench_embedded.py`` drives.

Arrows point one way: these modules import the receptor model and the chain, never the
reverse (:func:`spindle.chain.make_chain` and :func:`spindle.simulate` load them on demand).
"""
