"""The spindle bank the wrappers drive: it needs no MuJoCo, so it lives in the chain's room
(:mod:`spindle.chain.driver`); this import path is kept for existing code."""

from spindle.chain.driver import COUNTERS, ConstantFusimotor, SpindleDriver, TemplateFusimotor
from spindle.renamed import renamed_attribute

__all__ = ["COUNTERS", "ConstantFusimotor", "SpindleDriver", "TemplateFusimotor"]

_RENAMED = {"SpindleBank": "SpindleDriver"}  # renamed-from: the old names (spindle.renamed)


def __getattr__(name: str) -> object:
    return renamed_attribute(__name__, name, _RENAMED, globals())
