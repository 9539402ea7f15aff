"""What the simulated servo's shaft does: its angle and its torque over time, looped.

A :class:`ServoTrack` is one period of a repeated motion on a fine grid: the elbow angle and
the joint torque the servo must deliver (MuJoCo inverse dynamics of ``models/elbow.xml`` with
its muscles off: gravity, inertia, joint damping). The virtual servo and the simulated-elbow
source read it at any time (the period repeats); :class:`~proprio_env.body.encoder.Encoder` adds
the reading model on top.

Two tracks: :func:`scripted_track` (the demo's command, :func:`~proprio_env.body.servo_motion.
triangle_deg`, taken as the angle) and :func:`elbow_track` (the same command driven through the
model's position servo, :func:`~proprio_env.body.servo_motion.drive_servo`: the angle MuJoCo's arm
really reaches, lagging and rounding the command).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from proprio_env.body.model import JOINT, load_model
from proprio_env.body.servo_motion import drive_servo, servo_full_scale_Nm, triangle_deg

TRACKS = ("scripted", "elbow")


@dataclass(frozen=True)
class ServoTrack:
    """One period of a looped motion.

    Attributes:
        t_s: (T,) grid times from 0 (s); the motion repeats every ``period_s``.
        angle_deg: (T,) elbow angle (deg).
        torque_Nm: (T,) joint torque the servo delivers (N m, + towards flexion).
        full_scale_Nm: the torque read as full load (1023): the model servo's force range.
        period_s: the repeat period (s).
    """

    t_s: np.ndarray
    angle_deg: np.ndarray
    torque_Nm: np.ndarray
    full_scale_Nm: float
    period_s: float

    def at(self, t_s: float) -> tuple[float, float, float]:
        """Angle (deg), angular speed (deg/s) and load fraction (signed, of full scale) at
        ``t_s`` (any time: the period repeats)."""
        phase = float(t_s) % self.period_s
        i = min(int(phase / (self.t_s[1] - self.t_s[0])), self.t_s.size - 2)
        w = (phase - self.t_s[i]) / (self.t_s[i + 1] - self.t_s[i])
        angle = self.angle_deg[i] + w * (self.angle_deg[i + 1] - self.angle_deg[i])
        speed = (self.angle_deg[i + 1] - self.angle_deg[i]) / (self.t_s[i + 1] - self.t_s[i])
        torque = self.torque_Nm[i] + w * (self.torque_Nm[i + 1] - self.torque_Nm[i])
        load = max(-1.0, min(1.0, torque / self.full_scale_Nm))
        return float(angle), float(speed), float(load)


def _command_periods(model, periods: int) -> tuple[np.ndarray, np.ndarray, float]:
    """The demo's triangle command over ``periods`` periods on the model's time step."""
    dt = model.opt.timestep
    period = 2 * (110.0 - 20.0) / 130.0  # triangle_deg's defaults
    n = round(periods * period / dt)
    t = np.arange(n) * dt
    return t, triangle_deg(t), period


def _one_period(t: np.ndarray, y: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """The middle period of a periodic signal sampled on ``t`` (the ends carry the
    moving-average's edge and the servo's start-up), closed: its last point is its first."""
    dt = t[1] - t[0]
    n = round(period / dt)
    i0 = round(period / dt)
    grid = np.arange(n + 1) * dt
    seg = y[i0:i0 + n + 1].copy()
    seg[-1] = seg[0]
    return grid, seg


def _inverse_torque_Nm(model, angle_deg: np.ndarray, dt_s: float) -> np.ndarray:
    """Joint torque that makes the (periodic) angle trace happen: mj_inverse with muscles off."""
    import mujoco

    model.opt.disableactuator = 1 << 1
    data = mujoco.MjData(model)
    joint = model.joint(JOINT).id
    qadr, dadr = model.jnt_qposadr[joint], model.jnt_dofadr[joint]
    q = np.radians(angle_deg)
    # periodic central differences (the last point repeats the first)
    qp = np.roll(q[:-1], -1)
    qm = np.roll(q[:-1], 1)
    qd = (qp - qm) / (2 * dt_s)
    qdd = (qp - 2 * q[:-1] + qm) / dt_s**2
    torque = np.empty(q.size - 1)
    for i in range(q.size - 1):
        data.qpos[qadr], data.qvel[dadr], data.qacc[dadr] = q[i], qd[i], qdd[i]
        mujoco.mj_inverse(model, data)
        torque[i] = data.qfrc_inverse[dadr]
    return np.append(torque, torque[0])


def scripted_track() -> ServoTrack:
    """The demo's command (20-110 deg at 130 deg/s, rounded corners) taken as the angle."""
    model = load_model()
    t, command, period = _command_periods(model, 3)
    grid, angle = _one_period(t, command, period)
    torque = _inverse_torque_Nm(model, angle, grid[1] - grid[0])
    return ServoTrack(grid, angle, torque, servo_full_scale_Nm(model), grid[-1])


def elbow_track() -> ServoTrack:
    """The demo's command driven through the MuJoCo elbow's position servo: the angle the arm
    reaches (third period: the start-up transient has gone)."""
    model = load_model()
    t, command, period = _command_periods(model, 4)
    motion = drive_servo(command, model)
    grid, _ = _one_period(t, command, period)
    n = grid.size - 1
    i0 = 2 * n
    angle = motion.angle_deg[i0:i0 + n + 1].copy()
    angle[-1] = angle[0]
    torque = _inverse_torque_Nm(model, angle, grid[1] - grid[0])
    return ServoTrack(grid, angle, torque, servo_full_scale_Nm(model), grid[-1])


def make_track(name: str) -> ServoTrack:
    """The track called ``name`` (one of :data:`TRACKS`)."""
    if name == "scripted":
        return scripted_track()
    if name == "elbow":
        return elbow_track()
    raise ValueError(f"track={name!r} is not one of {TRACKS}")
