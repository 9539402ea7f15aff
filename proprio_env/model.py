"""Where the MJCF elbow lives and how to load it.

``models/elbow.xml`` is Arm26's elbow (Holzbaur et al. 2005, CC BY 3.0) with the OpenSim
names: hinge ``r_elbow_flex`` (0-130 deg), spatial tendons and muscle actuators ``BRA`` and
``TRImed``, and the position servo ``r_elbow_servo``. MuJoCo is imported lazily so that
``model_path()`` works without it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from spindle.length_fits import default_model_path

if TYPE_CHECKING:
    import mujoco

__all__ = ["JOINT", "MUSCLES", "SERVO", "load_model", "model_path"]

JOINT = "r_elbow_flex"
"""Name of the elbow hinge (OpenSim coordinate name)."""
MUSCLES = ("BRA", "TRImed")
"""Muscles in the order used on every muscle axis of the package."""
SERVO = "r_elbow_servo"
"""Name of the position actuator of the servo-driven prosthesis mode."""


def model_path() -> Path:
    """Path of ``elbow.xml`` (source checkout, editable or wheel install)."""
    return default_model_path()


def load_model(path: str | Path | None = None) -> mujoco.MjModel:
    """Compile ``elbow.xml`` (or the MJCF at ``path``) into a ``mujoco.MjModel``."""
    import mujoco

    return mujoco.MjModel.from_xml_path(str(path if path is not None else model_path()))
