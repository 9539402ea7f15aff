"""Gymnasium envs of the elbow with spindle afferents (imports MuJoCo and Gymnasium).

- :class:`ElbowReachEnv` (``proprio_env/ElbowReach-v0``): muscle-driven;
- :class:`ProsthesisElbowEnv` (``proprio_env/ProsthesisElbow-v0``): servo-driven prosthesis
  with the encoder chain.
"""

from proprio_env.envs.afferents import SOURCES, AfferentReadout
from proprio_env.envs.base import RATE_SCALE_PPS, ElbowProprioEnv
from proprio_env.envs.elbow_reach import ElbowReachEnv
from proprio_env.envs.prosthesis_elbow import ProsthesisElbowEnv

__all__ = ["RATE_SCALE_PPS", "SOURCES", "AfferentReadout", "ElbowProprioEnv", "ElbowReachEnv",
           "ProsthesisElbowEnv"]
