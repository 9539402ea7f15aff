"""The spindle bank the wrappers drive: it needs no MuJoCo, so it lives in the chain's room
(:mod:`spindle.chain.bank`); this import path is kept for existing code."""

from spindle.chain.bank import COUNTERS, ConstantFusimotor, SpindleBank, TemplateFusimotor

__all__ = ["COUNTERS", "ConstantFusimotor", "SpindleBank", "TemplateFusimotor"]
