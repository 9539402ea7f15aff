"""Exact muscle-length model: MuJoCo tendon (MTU) length -> normalised fibre length.

MuJoCo gives the musculotendon path length of ``BRA`` and ``TRImed``. With a rigid tendon at
its slack length and OpenSim's constant-width pennation (the fibre's perpendicular extent
h = L0 sin(alpha0) is constant), the fibre length is

    l_f = sqrt((l_mtu - l_ts)^2 + h^2),     L = l_f / L0,

and its velocity dL/dt = cos(alpha) * (dl_mtu/dt) / L0 with cos(alpha) = (l_mtu - l_ts) / l_f.
MuJoCo's own muscle normalisation, (l_mtu - l_ts) / L0, is the fibre length *along the
tendon*, short of the fibre length by up to 0.02 L0 for TRImed (alpha0 = 9 deg); BRA has no
pennation and the two agree.

The rigid tendon is the one approximation against OpenSim's passive equilibrium (elastic
tendon at activation 0.01): the tendon there stretches 0.2-0.6 %, i.e. fibres up to 0.004 L0
shorter than here.

Units: m, m/s, rad; normalised lengths in L0, velocities in L0/s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from proprio_env.body.model import JOINT, MUSCLES

if TYPE_CHECKING:
    import mujoco

__all__ = [
    "FibreLengths",
    "MuscleGeometry",
    "Sweep",
    "check_angle_rad",
    "elbow_range_rad",
    "fibre_length_L0",
    "fibre_state",
    "fibre_velocity_L0_s",
    "muscle_geometry",
    "pennation_rad",
    "sweep",
]


@dataclass(frozen=True)
class MuscleGeometry:
    """Length parameters of one muscle (Arm26 names and values).

    Parameters
    ----------
    name : str
        Muscle (and tendon, actuator) name.
    optimal_fibre_length_m : float
        L0, m.
    tendon_slack_length_m : float
        Tendon length (m) at which it starts to carry force; rigid here.
    pennation_at_optimal_rad : float
        Pennation angle (rad) at fibre length L0.
    """

    name: str
    optimal_fibre_length_m: float
    tendon_slack_length_m: float
    pennation_at_optimal_rad: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.optimal_fibre_length_m) and self.optimal_fibre_length_m > 0):
            raise ValueError(f"{self.name}: optimal_fibre_length_m must be finite and > 0")
        if not (np.isfinite(self.tendon_slack_length_m) and self.tendon_slack_length_m >= 0):
            raise ValueError(f"{self.name}: tendon_slack_length_m must be finite and >= 0")
        if not 0 <= self.pennation_at_optimal_rad < np.pi / 2:
            raise ValueError(f"{self.name}: pennation_at_optimal_rad must be in [0, pi/2)")

    @property
    def width_m(self) -> float:
        """Constant perpendicular extent of the fibres h = L0 sin(alpha0), m."""
        return self.optimal_fibre_length_m * float(np.sin(self.pennation_at_optimal_rad))


def _along_tendon_m(mtu_length_m: np.ndarray | float, geometry: MuscleGeometry) -> np.ndarray:
    mtu = np.asarray(mtu_length_m, dtype=float)
    if not np.all(np.isfinite(mtu)):
        raise ValueError(f"{geometry.name}: MTU length must be finite (got NaN or inf)")
    along = mtu - geometry.tendon_slack_length_m
    if np.any(along <= 0):
        raise ValueError(
            f"{geometry.name}: MTU length {mtu.min():.6g} m is not longer than the tendon "
            f"slack length {geometry.tendon_slack_length_m:.6g} m"
        )
    return along


def _fibre_length(along_m, width_m, optimal_m):
    return np.hypot(along_m, width_m) / optimal_m


def fibre_length_L0(mtu_length_m: np.ndarray | float, geometry: MuscleGeometry) -> np.ndarray:
    """Normalised fibre length (L0) for MTU length(s) ``mtu_length_m`` (m), same shape."""
    along = _along_tendon_m(mtu_length_m, geometry)
    return _fibre_length(along, geometry.width_m, geometry.optimal_fibre_length_m)


class FibreLengths:
    """:func:`fibre_length_L0` of several muscles at once: called with MTU lengths (..., m)
    (m), the last axis in the order of ``geometries``, returns fibre lengths (..., m) (L0).
    The same checks and errors, in a few array operations for all muscles (the envs call it
    at every step).
    """

    def __init__(self, geometries: tuple[MuscleGeometry, ...]) -> None:
        self.geometries = tuple(geometries)
        self._slack_m, self._width_m, self._optimal_m = (
            np.array([getattr(g, name) for g in self.geometries])
            for name in ("tendon_slack_length_m", "width_m", "optimal_fibre_length_m"))

    def __call__(self, mtu_length_m: np.ndarray) -> np.ndarray:
        mtu = np.asarray(mtu_length_m, dtype=float)
        along = mtu - self._slack_m
        # NaN fails both comparisons; a bad length is reported by the one-muscle function
        if along.size and not (along.min() > 0.0 and along.max() < np.inf):
            for j, g in enumerate(self.geometries):
                _along_tendon_m(mtu[..., j], g)
        return _fibre_length(along, self._width_m, self._optimal_m)


def pennation_rad(mtu_length_m: np.ndarray | float, geometry: MuscleGeometry) -> np.ndarray:
    """Pennation angle (rad) for MTU length(s) ``mtu_length_m`` (m), same shape."""
    along = _along_tendon_m(mtu_length_m, geometry)
    return np.arctan2(geometry.width_m, along)


def fibre_velocity_L0_s(
    mtu_length_m: np.ndarray | float,
    mtu_velocity_m_s: np.ndarray | float,
    geometry: MuscleGeometry,
) -> np.ndarray:
    """Normalised fibre velocity (L0/s), lengthening positive, for MTU length (m) and velocity
    (m/s) of broadcastable shapes."""
    along = _along_tendon_m(mtu_length_m, geometry)
    vel = np.asarray(mtu_velocity_m_s, dtype=float)
    if not np.all(np.isfinite(vel)):
        raise ValueError(f"{geometry.name}: MTU velocity must be finite (got NaN or inf)")
    cos_alpha = along / np.hypot(along, geometry.width_m)
    return cos_alpha * vel / geometry.optimal_fibre_length_m


def muscle_geometry(model: mujoco.MjModel, name: str) -> MuscleGeometry:
    """Read a muscle's L0 and tendon slack length from its MJCF actuator and its pennation
    from the custom numeric ``<name>_pennation_at_optimal_rad``.

    MuJoCo's muscle normalisation is L = range0 + (l - lengthrange0) / L0 with
    L0 = (lengthrange1 - lengthrange0) / (range1 - range0); the slack length is
    lengthrange0 - range0 * L0.
    """
    import mujoco

    act = model.actuator(name)
    lr0, lr1 = (float(v) for v in act.lengthrange)
    r0, r1 = (float(v) for v in model.actuator_gainprm[act.id, :2])
    optimal = (lr1 - lr0) / (r1 - r0)
    key = f"{name}_pennation_at_optimal_rad"
    numeric = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, key)
    if numeric < 0:
        raise ValueError(f"model has no custom numeric {key}")
    pennation = float(model.numeric_data[model.numeric_adr[numeric]])
    return MuscleGeometry(
        name=name,
        optimal_fibre_length_m=optimal,
        tendon_slack_length_m=lr0 - r0 * optimal,
        pennation_at_optimal_rad=pennation,
    )


def elbow_range_rad(model: mujoco.MjModel) -> tuple[float, float]:
    """The elbow hinge's range (rad)."""
    lo, hi = model.joint(JOINT).range
    return float(lo), float(hi)


def check_angle_rad(angle_rad: np.ndarray | float, range_rad: tuple[float, float]) -> np.ndarray:
    """``angle_rad`` as a float array; ValueError if it is NaN/inf or outside ``range_rad``."""
    angle = np.asarray(angle_rad, dtype=float)
    if not np.all(np.isfinite(angle)):
        raise ValueError("elbow angle must be finite (got NaN or inf)")
    lo, hi = range_rad
    if np.any((angle < lo) | (angle > hi)):
        bad = float(angle[(angle < lo) | (angle > hi)].ravel()[0])
        raise ValueError(
            f"elbow angle {bad:.6g} rad ({np.degrees(bad):.4g} deg) is outside the joint range "
            f"[{lo:.6g}, {hi:.6g}] rad"
        )
    return angle


@dataclass(frozen=True)
class Sweep:
    """Exact model evaluated at a set of elbow angles; arrays are ``(n_angles, n_muscles)``."""

    angle_rad: np.ndarray
    muscles: tuple[str, ...]
    mtu_length_m: np.ndarray
    moment_arm_m: np.ndarray
    fibre_length_L0: np.ndarray
    pennation_rad: np.ndarray


def sweep(
    model: mujoco.MjModel, angle_rad: np.ndarray, muscles: tuple[str, ...] = MUSCLES
) -> Sweep:
    """MTU lengths (m), moment arms (m, flexor positive), fibre lengths (L0) and pennation
    (rad) at elbow angles ``angle_rad`` (rad, 1-D, within the joint range), kinematically.

    The moment arm is -d l_mtu / d angle, obtained as minus the tendon velocity at unit
    joint velocity (this works whatever the storage of MuJoCo's tendon Jacobian).
    """
    import mujoco

    angle = np.atleast_1d(check_angle_rad(angle_rad, elbow_range_rad(model)))
    if angle.ndim != 1:
        raise ValueError("angle_rad must be a scalar or 1-D")
    data = mujoco.MjData(model)
    qadr = model.joint(JOINT).qposadr[0]
    vadr = model.joint(JOINT).dofadr[0]
    tendon_ids = [model.tendon(m).id for m in muscles]
    length = np.empty((angle.size, len(muscles)))
    velocity = np.empty_like(length)
    for i, q in enumerate(angle):
        data.qpos[qadr] = q
        data.qvel[:] = 0.0
        data.qvel[vadr] = 1.0
        mujoco.mj_fwdPosition(model, data)
        mujoco.mj_fwdVelocity(model, data)
        length[i] = data.ten_length[tendon_ids]
        velocity[i] = data.ten_velocity[tendon_ids]
    geoms = [muscle_geometry(model, m) for m in muscles]
    return Sweep(
        angle_rad=angle,
        muscles=tuple(muscles),
        mtu_length_m=length,
        moment_arm_m=-velocity,
        fibre_length_L0=np.stack(
            [fibre_length_L0(length[:, j], g) for j, g in enumerate(geoms)], axis=-1
        ),
        pennation_rad=np.stack(
            [pennation_rad(length[:, j], g) for j, g in enumerate(geoms)], axis=-1
        ),
    )


def fibre_state(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    geometries: tuple[MuscleGeometry, ...] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Fibre lengths (L0) and velocities (L0/s), shape ``(n_muscles,)`` in ``MUSCLES`` order,
    from ``data.ten_length`` / ``data.ten_velocity``.

    Those are filled by ``mj_forward`` (or ``mj_fwdPosition`` + ``mj_fwdVelocity``); after
    ``mj_step`` they describe the state *before* the step, so call ``mj_forward`` first when
    the post-step value is wanted. Pass ``geometries`` (from :func:`muscle_geometry`) to
    avoid re-reading them at every call.
    """
    if geometries is None:
        geometries = tuple(muscle_geometry(model, m) for m in MUSCLES)
    ids = [model.tendon(g.name).id for g in geometries]
    length = np.array(
        [fibre_length_L0(data.ten_length[i], g) for i, g in zip(ids, geometries, strict=True)]
    )
    velocity = np.array(
        [
            fibre_velocity_L0_s(data.ten_length[i], data.ten_velocity[i], g)
            for i, g in zip(ids, geometries, strict=True)
        ]
    )
    return length, velocity
