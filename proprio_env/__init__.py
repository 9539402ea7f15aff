"""MuJoCo side of the proprioception toolkit: the Arm26 elbow model and its exact muscle lengths.

Kept light on purpose: importing the package does not import MuJoCo or Gymnasium; the
submodules do (``proprio_env.model``, ``proprio_env.muscle_length``).
"""

from proprio_env.model import JOINT, MUSCLES, model_path

__all__ = ["JOINT", "MUSCLES", "model_path"]
