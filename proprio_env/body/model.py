"""Where the MJCF elbow lives and how to load it.

``models/elbow.xml`` is Arm26's elbow (Holzbaur et al. 2005, CC BY 3.0) with the OpenSim
names: hinge ``r_elbow_flex`` (0-130 deg), spatial tendons and muscle actuators ``BRA`` and
``TRImed``, and the position servo ``r_elbow_servo``. MuJoCo is imported lazily so that
``model_path()`` works without it.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from spindle.chain.config import MUSCLES

if TYPE_CHECKING:
    import mujoco

__all__ = ["FOREARM", "JOINT", "MODEL_FILENAME", "MUSCLES", "SERVO", "load_model", "model_path",
           "models_dir"]

JOINT = "r_elbow_flex"
"""Name of the elbow hinge (OpenSim coordinate name)."""
SERVO = "r_elbow_servo"
"""Name of the position actuator of the servo-driven prosthesis mode."""
FOREARM = "r_ulna_radius_hand"
"""Name of the forearm body and its capsule geom."""
OBSTACLE = "obstacle"
"""Name of the optional obstacle geom (see :func:`load_model`)."""
OBSTACLE_RADIUS_M = 0.02
OBSTACLE_DISTANCE_M = 0.2
"""The obstacle is a sphere of this radius touching the forearm this far from the elbow."""


MODEL_FILENAME = "elbow.xml"
_DATA_PACKAGE = "proprio_models"


def models_dir() -> Path:
    """Folder holding ``elbow.xml``, ``length_fits.json`` and the oracles' data.

    A source checkout (plain or editable install) uses the repository's ``models/`` next to
    this package; a wheel install uses the installed data package ``proprio_models``.
    """
    checkout = Path(__file__).resolve().parent.parent / "models"
    if (checkout / MODEL_FILENAME).is_file():
        return checkout
    try:
        installed = resources.files(_DATA_PACKAGE)
    except ModuleNotFoundError as err:
        raise FileNotFoundError(
            f"cannot find the models folder: neither {checkout} nor an installed "
            f"'{_DATA_PACKAGE}' package exists; reinstall proprio-elbow"
        ) from err
    # Wheels install plain files, so the traversable is a real directory.
    return Path(str(installed))


def model_path() -> Path:
    """Path of ``elbow.xml`` (source checkout, editable or wheel install)."""
    return models_dir() / MODEL_FILENAME


def load_model(
    path: str | Path | None = None, *, obstacle_deg: float | None = None
) -> mujoco.MjModel:
    """Compile ``elbow.xml`` (or the MJCF at ``path``) into a ``mujoco.MjModel``.

    ``obstacle_deg`` adds a fixed sphere that stops elbow *flexion* at that angle (deg): it
    touches the forearm capsule, :data:`OBSTACLE_DISTANCE_M` from the elbow, when the joint is
    at ``obstacle_deg``. Only the forearm and the obstacle collide (soft contact, 4 ms time
    constant, so the forearm sinks into it by a fraction of a degree under the servo's force).
    """
    import mujoco

    source = str(path if path is not None else model_path())
    if obstacle_deg is None:
        return mujoco.MjModel.from_xml_path(source)
    plain = mujoco.MjModel.from_xml_path(source)
    lo, hi = (math.degrees(x) for x in plain.jnt_range[plain.joint(JOINT).id])
    angle = float(obstacle_deg)
    if not (math.isfinite(angle) and lo < angle < hi):
        raise ValueError(f"obstacle_deg={obstacle_deg!r} must lie inside the joint range "
                         f"({lo:g}, {hi:g}) deg")
    # Where the sphere's centre must be: on the forearm's sweep, ahead of the contact angle by
    # the angle whose chord clears the sum of the two radii.
    forearm_radius = float(plain.geom_size[plain.geom(FOREARM).id][0])
    ahead = math.asin((OBSTACLE_RADIUS_M + forearm_radius) / OBSTACLE_DISTANCE_M)
    data = mujoco.MjData(plain)
    data.qpos[plain.jnt_qposadr[plain.joint(JOINT).id]] = math.radians(angle) + ahead
    mujoco.mj_kinematics(plain, data)
    body = plain.body(FOREARM).id
    local = np.array([0.0, -OBSTACLE_DISTANCE_M, 0.0])  # along the forearm capsule
    centre = data.xpos[body] + data.xmat[body].reshape(3, 3) @ local

    spec = mujoco.MjSpec.from_file(source)
    forearm = spec.geom(FOREARM)
    forearm.contype, forearm.conaffinity = 2, 0
    spec.worldbody.add_geom(
        name=OBSTACLE, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[OBSTACLE_RADIUS_M, 0, 0],
        pos=centre, contype=0, conaffinity=2, rgba=[0.8, 0.3, 0.2, 1.0],
        solref=[0.004, 1.0], group=1,
    )
    return spec.compile()
