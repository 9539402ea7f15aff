"""The spindle bank the wrappers drive: it needs no MuJoCo, so it lives in the chain's room
(:mod:`spindle.chain.driver`); this import path is kept for existing code."""

from spindle.chain.driver import COUNTERS, ConstantFusimotor, SpindleDriver, TemplateFusimotor

__all__ = ["COUNTERS", "ConstantFusimotor", "SpindleDriver", "TemplateFusimotor"]
