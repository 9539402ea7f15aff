"""The afferents of recorded joint motion: replay ``qpos`` through a model's muscle paths."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral

import mujoco
import numpy as np

from proprio_env.body.force_sense import max_forces_N
from proprio_env.wrappers.muscles import ActuatorKinematics, find_muscles
from spindle.backends import DEFAULT_BACKEND
from spindle.chain.driver import (
    COUNTERS,
    ConstantFusimotor,
    SpindleDriver,
    TemplateFusimotor,
)
from spindle.core import SLEW_LIMIT_L0_S
from spindle.params import HUMAN, SpindleParams
from spindle.substeps import substeps
from spindle.tendon_organ import MAX_FORCE_N, check_step
from spindle.tendon_organ import simulate as tendon_simulate
from spindle.tendon_organ_params import HUMAN as TENDON_HUMAN
from spindle.tendon_organ_params import TendonOrganParams, force_scales_N

UNIFORM_TOLERANCE = 1e-6
"""Largest relative spread of the sample intervals of a trajectory (it must be uniform)."""

CHUNK_SUBSTEPS = 4096
"""Spindle sub-steps per batched advance (at least one sample): bounds the sub-step buffers
of a long trajectory whatever its sample interval."""

MAX_TRAJECTORY_SUBSTEPS = 10_000_000
"""Default bound on the spindle sub-steps of one trajectory (``max_substeps``): 10^7 sub-steps
of 1 ms are 2.8 h of motion. More (times in ms taken as s, a corrupted time axis) is refused
with ``ValueError`` before any work, since it would run for minutes to hours."""


@dataclass(frozen=True)
class TrajectoryAfferents:
    """Per-sample signals of every muscle; arrays are (T, M) unless noted.

    Attributes:
        t_s: (T,) sample times.
        muscle_names: the muscles, in column order.
        ia_pps, ii_pps: afferent rates (pps).
        length_L0: lengths as fed to the spindles (clamped to 0.5-1.5 L0, slew-limited).
        measured_length_L0: MuJoCo's normalised lengths, unclamped.
        velocity_L0_s: normalised velocities (as fed: clipped to the slew limit).
        gamma_static_pps, gamma_dynamic_pps: the fusimotor drive.
        counters: the bank's per-muscle counters (M,) over the whole trajectory.
        force_N: the tendon forces given (``force_N_t``), or None.
        ib_pps: Ib of the muscles' tendon organs along those forces, or None without them.
    """

    t_s: np.ndarray
    muscle_names: tuple[str, ...]
    ia_pps: np.ndarray
    ii_pps: np.ndarray
    length_L0: np.ndarray
    measured_length_L0: np.ndarray
    velocity_L0_s: np.ndarray
    gamma_static_pps: np.ndarray
    gamma_dynamic_pps: np.ndarray
    counters: dict[str, np.ndarray]
    force_N: np.ndarray | None = None
    ib_pps: np.ndarray | None = None


def afferents_from_trajectory(
    model: mujoco.MjModel,
    qpos_t: np.ndarray,
    t_s: np.ndarray,
    qvel_t: np.ndarray | None = None,
    muscles: Sequence[str] | None = None,
    params: SpindleParams = HUMAN,
    fusimotor: ConstantFusimotor | TemplateFusimotor | None = None,
    method: str = "trapezoidal",
    step_s: float | None = None,
    max_speed_L0_s: float = SLEW_LIMIT_L0_S,
    backend: str = DEFAULT_BACKEND,
    max_substeps: int = MAX_TRAJECTORY_SUBSTEPS,
    force_N_t: np.ndarray | None = None,
    ib_params: TendonOrganParams = TENDON_HUMAN,
) -> TrajectoryAfferents:
    """Ia and II of every muscle of ``model`` along recorded joint motion.

    Each sample's muscle lengths come from ``qpos`` through the model's kinematics, tendons
    and transmissions (no dynamics: the motion is imposed, e.g. motion capture or OpenSim
    inverse kinematics mapped to the model's joints); the velocities from ``qvel_t`` through
    the moment arms if given, else by differentiating the lengths in time (second order,
    ``numpy.gradient``). The spindles start at equilibrium at the first sample and follow
    the same rules and sub-steps as :class:`~proprio_env.wrappers.SpindleAfferents` between
    samples.

    Args:
        model: the MuJoCo model.
        qpos_t: (T, nq) joint positions.
        t_s: (T,) sample times, uniformly spaced.
        qvel_t: (T, nv) joint velocities, or None.
        muscles, params, fusimotor, method, step_s, max_speed_L0_s, backend: as the
            wrapper's.
        max_substeps: the most spindle sub-steps (of at most ``step_s``) the trajectory may
            take in all; ``ValueError`` naming the count and the limit beyond it, or beyond
            ``spindle.simulation.MAX_SUBSTEPS`` in one sample interval (both checked before any
            work).
        force_N_t: (T, M) tendon forces (N, tension positive) of the muscles at the samples
            (e.g. OpenSim's static optimisation, or a recorded ``info["tendon_force_N"]``), or
            None. Only with them does the result hold Ib: the motion alone does not give the
            forces (they depend on the activations, which a replay of ``qpos`` does not
            have). Ib is :func:`spindle.tendon_organ.simulate` on them (one organ step per
            sample interval, at most ``spindle.tendon_organ.MAX_STEP_S``), from rest at the
            first sample, with the force scale from each muscle's ``gainprm[2]``. Finite,
            at most ``MAX_FORCE_N``; a negative force is a slack tendon (0).
        ib_params: the tendon-organ preset (default human).

    Returns:
        :class:`TrajectoryAfferents`.
    """
    q, t, qv = _checked_trajectory(model, qpos_t, t_s, qvel_t)
    dt = np.diff(t)
    muscle_set = find_muscles(model, muscles)
    forces, scales = _checked_forces(model, force_N_t, dt, muscle_set, ib_params)
    bank = SpindleDriver(1, muscle_set.range_low_L0, muscle_set.range_high_L0, params,
                       fusimotor, method, step_s, max_speed_L0_s, backend)
    per_interval = _check_work(dt, bank.step_s, max_substeps)
    L, V = _normalised_lengths(model, muscle_set, q, t, qv)

    bank.reset(None, t[:1], L[:1], V[:1])
    out = {key: np.empty_like(L) for key in ("ia_pps", "ii_pps", "length_L0", "velocity_L0_s",
                                              "gamma_static_pps", "gamma_dynamic_pps")}
    out["ia_pps"][0], out["ii_pps"][0] = bank.ia_pps[0], bank.ii_pps[0]
    out["length_L0"][0], out["velocity_L0_s"][0] = bank.length_L0[0], bank.velocity_L0_s[0]
    out["gamma_static_pps"][0] = bank.gamma_static_pps[0]
    out["gamma_dynamic_pps"][0] = bank.gamma_dynamic_pps[0]
    chunk = max(1, CHUNK_SUBSTEPS // per_interval)
    for i0 in range(1, t.size, chunk):
        i1 = min(i0 + chunk, t.size)
        bank.advance(t[i0:i1, None], L[i0:i1, None], V[i0:i1, None], record=True)
        for key in out:
            out[key][i0:i1] = bank.knots[key][:, 0]
    counters = {name: bank.counters[name][0].copy() for name in COUNTERS}
    ib = (None if forces is None
          else tendon_simulate(forces, float(dt.mean()), scales, ib_params, backend))
    return TrajectoryAfferents(t_s=t.copy(), muscle_names=muscle_set.names,
                               measured_length_L0=L, counters=counters, force_N=forces,
                               ib_pps=ib, **out)


def _normalised_lengths(model: mujoco.MjModel, muscle_set, q: np.ndarray, t: np.ndarray,
                        qv: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(lengths L0, velocities L0/s), (T, M), of the samples: the velocities through the
    moment arms from ``qv``, or the lengths' time derivative (second order) without it."""
    kinematics = ActuatorKinematics(model, muscle_set.ids)
    zero = np.zeros(model.nv)
    length_m = np.empty((t.size, muscle_set.n))
    velocity_m_s = np.empty_like(length_m)
    for i in range(t.size):
        length_m[i], velocity_m_s[i] = kinematics.compute(
            q[i], zero if qv is None else qv[i])
    if qv is None:
        velocity_m_s = np.gradient(length_m, t, axis=0)
    return muscle_set.length_L0(length_m), muscle_set.velocity_L0_s(velocity_m_s)


def _checked_forces(model: mujoco.MjModel, force_N_t, dt_s: np.ndarray, muscle_set,
                    params: TendonOrganParams) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(forces (T, M) N, force scales (M,) N), or (None, None) without ``force_N_t``; shape,
    finiteness, the force limit and the sample interval (the organs' step) checked."""
    if force_N_t is None:
        return None, None
    forces = np.array(force_N_t, dtype=float)
    if forces.shape != (dt_s.size + 1, muscle_set.n):
        raise ValueError(f"force_N_t has shape {forces.shape}; expected "
                         f"({dt_s.size + 1}, {muscle_set.n}) (samples, muscles)")
    if not np.all(np.isfinite(forces)) or np.any(forces > MAX_FORCE_N):
        raise ValueError(f"force_N_t must be finite and at most MAX_FORCE_N = "
                         f"{MAX_FORCE_N} N (max {np.nanmax(forces)!r})")
    check_step(float(dt_s.mean()))
    return forces, force_scales_N(params, max_forces_N(model, muscle_set.ids))


def _checked_trajectory(model: mujoco.MjModel, qpos_t, t_s, qvel_t
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(qpos, times, qvel or None) as float arrays, shapes, finiteness and uniform times
    checked."""
    q = np.asarray(qpos_t, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if q.ndim != 2 or q.shape[1] != model.nq or t.shape != (q.shape[0],):
        raise ValueError(f"qpos_t has shape {q.shape} and t_s {t.shape}; expected "
                         f"(T, {model.nq}) and (T,)")
    if t.size < 2:
        raise ValueError(f"a trajectory needs at least 2 samples, got {t.size}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise ValueError("qpos_t and t_s must be finite")
    dt = np.diff(t)
    if not (dt.min() > 0 and dt.max() - dt.min() <= UNIFORM_TOLERANCE * dt.mean()):
        raise ValueError(f"t_s must be increasing and uniform: sample intervals range over "
                         f"[{dt.min()!r}, {dt.max()!r}] s")
    qv = None
    if qvel_t is not None:
        qv = np.asarray(qvel_t, dtype=float)
        if qv.shape != (t.size, model.nv) or not np.all(np.isfinite(qv)):
            raise ValueError(f"qvel_t has shape {qv.shape}; expected finite (T, {model.nv})")
    return q, t, qv


def _check_work(dt_s: np.ndarray, step_s: float, max_substeps: object) -> int:
    """The spindle sub-steps per sample interval; ``ValueError`` if one interval needs more
    than ``spindle.simulation.MAX_SUBSTEPS`` or the whole trajectory more than
    ``max_substeps``."""
    from spindle.simulation import MAX_SUBSTEPS

    if isinstance(max_substeps, bool | np.bool_) or not isinstance(max_substeps, Integral) \
            or max_substeps < 1:
        raise ValueError(f"max_substeps={max_substeps!r} must be an integer >= 1")
    interval = float(dt_s.mean())
    k = substeps(interval, step_s)
    if k > MAX_SUBSTEPS:
        raise ValueError(f"the sample interval {interval!r} s needs {k} spindle sub-steps of "
                         f"{step_s!r} s, above the limit MAX_SUBSTEPS = {MAX_SUBSTEPS}; are "
                         "t_s in seconds?")
    total = k * dt_s.size
    if total > max_substeps:
        raise ValueError(f"the trajectory needs {total} spindle sub-steps ({dt_s.size} "
                         f"intervals of {interval!r} s, {k} sub-steps of at most {step_s!r} s "
                         f"each), above the limit max_substeps = {max_substeps}; are t_s in "
                         "seconds? (pass a larger max_substeps for a longer replay)")
    return k
