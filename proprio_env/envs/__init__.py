"""Gymnasium envs of the elbow with spindle afferents (imports MuJoCo and Gymnasium).

- :class:`ElbowReachEnv` (``proprio_env/ElbowReach-v0``): muscle-driven;
- :class:`ProsthesisElbowEnv` (``proprio_env/ProsthesisElbow-v0``): servo-driven prosthesis
  with the encoder chain;
- ``-v1`` of both: ``include_ib=True``, Ib of BRA and TRImed (tendon organs,
  :mod:`proprio_env.body.force_sense`) observed too.

Both are one env of :class:`~proprio_env.envs.core.EnvCore`, the one implementation of the
env step over n envs; ``gymnasium.make_vec`` builds its n-env view
(:mod:`proprio_env.envs.vector`).
"""

from proprio_env.envs.afferents import SOURCES, AfferentReadout
from proprio_env.envs.base import ElbowProprioEnv
from proprio_env.envs.core import RATE_SCALE_PPS, EnvCore
from proprio_env.envs.elbow_reach import ElbowReachEnv
from proprio_env.envs.prosthesis_elbow import ProsthesisElbowEnv

__all__ = ["RATE_SCALE_PPS", "SOURCES", "AfferentReadout", "ElbowProprioEnv", "ElbowReachEnv",
           "EnvCore", "ProsthesisElbowEnv"]
