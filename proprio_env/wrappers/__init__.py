"""Spindle afferents for any MuJoCo musculoskeletal model (imports MuJoCo and Gymnasium).

- :class:`SpindleAfferents`: a ``gymnasium.Wrapper`` adding Ia and II of every muscle to an
  env's observation (``afferents=("ia", "ii", "ib")`` adds the tendon organs' Ib; the
  tendon forces are in ``info`` either way);
- :class:`SpindleAfferentsVector`: the same for a ``gymnasium.vector.SyncVectorEnv``, every
  muscle of every env in one batched spindle state;
- :func:`afferents_from_trajectory`: the afferents of recorded joint motion (motion capture,
  OpenSim IK) replayed through a model;
- :class:`ConstantFusimotor`, :class:`TemplateFusimotor`: the fusimotor options.

``docs/wrapper.md`` describes what the wrappers assume about a model and their rules.
"""

from proprio_env.wrappers.muscles import MuscleSet, find_muscles
from proprio_env.wrappers.single import SpindleAfferents
from proprio_env.wrappers.trajectory import TrajectoryAfferents, afferents_from_trajectory
from proprio_env.wrappers.vector import SpindleAfferentsVector
from spindle.chain.driver import ConstantFusimotor, SpindleDriver, TemplateFusimotor

__all__ = ["ConstantFusimotor", "MuscleSet", "SpindleAfferents", "SpindleAfferentsVector",
           "SpindleDriver", "TemplateFusimotor", "TrajectoryAfferents",
           "afferents_from_trajectory", "find_muscles"]
