"""The prosthesis in real time on real interfaces (docs/runtime.md).

A source of readings (:mod:`~proprio_env.runtime.sources`: a Dynamixel AX-12 through
``dynamixel_sdk``, the virtual servo of :mod:`~proprio_env.runtime.virtual_servo`, a
simulated elbow, a replay) drives the chain at 500 Hz in :class:`~proprio_env.runtime.loop.
Runtime`; stages (:mod:`~proprio_env.runtime.stages`) make the rate stream and an optional
pulse encoder its events; sinks (:mod:`~proprio_env.runtime.sinks`) stream them on Lab
Streaming Layer, hand them to a callback and log every reading. ``dynamixel_sdk`` and
``pylsl`` are the ``runtime`` extra, imported only by the sources and sinks that need them.
"""

from proprio_env.runtime.loop import Runtime
from proprio_env.runtime.sinks import CallbackSink, CsvLog, LslSink, Row
from proprio_env.runtime.sources import DynamixelSource, Reading, ReplaySource, SimulatedElbowSource
from proprio_env.runtime.stages import LoadStage, PulseEncoder, RuntimeSample, SpindleStage, Stage

__all__ = ["CallbackSink", "CsvLog", "DynamixelSource", "LoadStage", "LslSink", "PulseEncoder",
           "Reading", "ReplaySource", "Row", "Runtime", "RuntimeSample", "SimulatedElbowSource",
           "SpindleStage", "Stage"]
