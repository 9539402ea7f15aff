"""Drive the MuJoCo elbow with its position servo and record the motion it really makes.

The prosthesis' own servo moves the forearm; the elbow angle and the exact (MuJoCo tendon)
fibre lengths are recorded at every physics step. Muscles are disabled (a passive prosthetic
arm), gravity acts, so the recorded angle lags and rounds the commanded one as a real servo
would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from proprio_env.body.model import JOINT, MUSCLES, SERVO, load_model
from proprio_env.body.muscle_length import fibre_state, muscle_geometry
from spindle.chain.sensor import AX12_LOAD, LoadParams


@dataclass(frozen=True)
class ServoMotion:
    """A recorded servo-driven motion; arrays have time on axis 0.

    Attributes:
        t_s: physics time (s), every model timestep.
        command_deg: the servo's target angle (deg).
        angle_deg: the elbow angle reached (deg).
        length_L0: (T, 2) exact normalised fibre lengths, BRA and TRImed.
        velocity_L0_s: (T, 2) their time derivatives.
        torque_Nm: the servo's joint torque (N m, flexion positive): MuJoCo's actuator force
            of the position servo (gear 1 on the hinge), what its load reading reports.
    """

    t_s: np.ndarray
    command_deg: np.ndarray
    angle_deg: np.ndarray
    length_L0: np.ndarray
    velocity_L0_s: np.ndarray
    torque_Nm: np.ndarray


def servo_full_scale_Nm(model) -> float:
    """The torque the model's position servo can exert (N m): its force range."""
    return float(np.max(np.abs(model.actuator_forcerange[model.actuator(SERVO).id])))


def servo_load_params(model=None) -> LoadParams:
    """The load reading of the model's servo: the AX-12's word and noise, full scale
    (1023) at :func:`servo_full_scale_Nm` (20 N m for ``models/elbow.xml``). It holds the
    Arm26 forearm against gravity with 2-5 N m, above an AX-12's 1.5 N m stall torque, so
    its load word spans its own range (what the virtual AX-12 of the runtime sends too)."""
    model = load_model() if model is None else model
    return LoadParams(max_torque_Nm=servo_full_scale_Nm(model),
                      noise_counts=AX12_LOAD.noise_counts, invalid_rate=AX12_LOAD.invalid_rate)


def triangle_deg(t_s: np.ndarray, low_deg: float = 20.0, high_deg: float = 110.0,
                 speed_deg_s: float = 130.0, corner_s: float = 0.05) -> np.ndarray:
    """Repeated flexion-extension between ``low_deg`` and ``high_deg`` at ``speed_deg_s``.

    Starts at ``low_deg`` flexing; the corners are rounded by a moving average over
    ``corner_s`` (a real joint cannot reverse instantly).
    """
    t_s = np.asarray(t_s, dtype=float)
    if not (high_deg > low_deg and speed_deg_s > 0 and corner_s >= 0):
        raise ValueError(
            f"need high_deg > low_deg, speed_deg_s > 0, corner_s >= 0; got {high_deg!r}, "
            f"{low_deg!r}, {speed_deg_s!r}, {corner_s!r}"
        )
    period = 2 * (high_deg - low_deg) / speed_deg_s
    phase = (t_s % period) / period
    tri = low_deg + (high_deg - low_deg) * (1 - np.abs(2 * phase - 1))
    if corner_s == 0 or t_s.size < 2:
        return tri
    k = max(1, round(corner_s / (t_s[1] - t_s[0])))
    padded = np.pad(tri, (k, k), mode="edge")
    return np.convolve(padded, np.ones(k) / k, mode="same")[k:-k]


def drive_servo(command_deg: np.ndarray, model=None) -> ServoMotion:
    """Run the servo through ``command_deg`` (one target per model timestep, deg).

    The arm starts at rest at the first target. Returns what MuJoCo measured after each step
    (the first row is the initial state).
    """
    import mujoco

    model = load_model() if model is None else model
    command = np.asarray(command_deg, dtype=float)
    if command.ndim != 1 or command.size < 1 or not np.all(np.isfinite(command)):
        raise ValueError("command_deg must be a non-empty 1-D array of finite angles")
    lo, hi = (math.degrees(x) for x in model.jnt_range[model.joint(JOINT).id])
    if command.min() < lo or command.max() > hi:
        raise ValueError(f"servo commands span {command.min()!r}..{command.max()!r} deg, "
                         f"outside the joint range {lo:.1f}..{hi:.1f} deg")
    # Muscles off (actuator group 1): a passive arm moved by its servo.
    model.opt.disableactuator = 1 << 1
    data = mujoco.MjData(model)
    qadr = model.jnt_qposadr[model.joint(JOINT).id]
    servo = model.actuator(SERVO).id
    geoms = tuple(muscle_geometry(model, m) for m in MUSCLES)
    data.qpos[qadr] = math.radians(command[0])
    data.ctrl[servo] = math.radians(command[0])  # (the first row's torque holds the arm there)
    mujoco.mj_forward(model, data)
    n = command.size
    angle = np.empty(n)
    length = np.empty((n, 2))
    velocity = np.empty((n, 2))
    torque = np.empty(n)
    for i in range(n):
        if i:
            data.ctrl[servo] = math.radians(command[i])
            mujoco.mj_step(model, data)
            mujoco.mj_forward(model, data)
        angle[i] = math.degrees(data.qpos[qadr])
        length[i], velocity[i] = fibre_state(model, data, geoms)
        torque[i] = data.actuator_force[servo]
    t = np.arange(n) * model.opt.timestep
    return ServoMotion(t, command, angle, length, velocity, torque)
