"""Which actuators are muscles, and their normalised fibre length and velocity from MuJoCo.

MuJoCo's muscle model (``mju_muscleGain``) normalises an actuator's length with its
``lengthrange`` and the gain parameters' ``range = gainprm[0:2]``:

    L0 = (lengthrange[1] - lengthrange[0]) / (range[1] - range[0])     (m)
    L  = range[0] + (actuator_length - lengthrange[0]) / L0            (L0)
    dL/dt = actuator_velocity / L0                                     (L0/s)

so ``lengthrange`` maps onto ``range``. This is the fibre length *along the tendon* of a
rigid-tendon, unpennated muscle: it ignores pennation (the fibre is longer than its
projection on the line of action, by up to 0.019 L0 for the elbow's TRImed at 9 deg) and
tendon compliance (MuJoCo's muscles have a rigid tendon; OpenSim's elastic tendon stretches
0.2-0.6 % at rest, fibres up to 0.004 L0 shorter). ``docs/wrapper.md`` has the measurement.

The lengths at a given state are computed on a scratch ``MjData`` (kinematics, tendons,
transmission: what ``mj_fwdPosition`` does minus collisions and inertia), so the env's own
``MjData`` is never touched: an env whose reward reads e.g. ``xpos`` after its physics steps
sees exactly what it would without the wrapper.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import mujoco
import numpy as np


@dataclass(frozen=True)
class MuscleSet:
    """The muscle actuators of a model and their length normalisation (arrays over muscles).

    Attributes:
        names: actuator names.
        ids: actuator ids, (M,).
        optimal_length_m: L0 (m), (M,).
        lengthrange_low_m: ``actuator_lengthrange[:, 0]`` (m), (M,).
        range_low_L0, range_high_L0: ``gainprm[0:2]``, the normalised lengths that
            ``lengthrange`` maps onto (L0), (M,).
        gear: ``actuator_gear[:, 0]``, (M,): actuator force x gear is the tendon's.
    """

    names: tuple[str, ...]
    ids: np.ndarray
    optimal_length_m: np.ndarray
    lengthrange_low_m: np.ndarray
    range_low_L0: np.ndarray
    range_high_L0: np.ndarray
    gear: np.ndarray

    @property
    def n(self) -> int:
        return len(self.names)

    @cached_property
    def columns(self) -> slice | np.ndarray:
        """The muscles' columns of a per-actuator array: a slice where the ids run
        consecutively (every muscle of myo-sim's models: a view, not a gather's copy), else
        :attr:`ids`."""
        first = int(self.ids[0])
        if np.array_equal(self.ids, np.arange(first, first + self.ids.size)):
            return slice(first, first + self.ids.size)
        return self.ids

    def length_L0(self, actuator_length_m: np.ndarray) -> np.ndarray:
        """MuJoCo's normalised length of actuator lengths (m), (..., M)."""
        return self.range_low_L0 + (actuator_length_m - self.lengthrange_low_m) \
            / self.optimal_length_m

    def tension_N(self, actuator_force: np.ndarray) -> np.ndarray:
        """The tendon tension (N, pulling positive) of MuJoCo's ``actuator_force`` (..., M):
        ``-gear * force`` (a MuJoCo muscle pulls with a negative force; the gear scales the
        actuator's force into its tendon's)."""
        return -self.gear * actuator_force

    def velocity_L0_s(self, actuator_velocity_m_s: np.ndarray) -> np.ndarray:
        """Normalised velocity (L0/s, lengthening positive) of actuator velocities, (..., M)."""
        return actuator_velocity_m_s / self.optimal_length_m


def is_muscle(model: mujoco.MjModel) -> np.ndarray:
    """(nu,) bool: actuators with muscle dynamics or a muscle gain."""
    return ((model.actuator_dyntype == mujoco.mjtDyn.mjDYN_MUSCLE)
            | (model.actuator_gaintype == mujoco.mjtGain.mjGAIN_MUSCLE))


def find_muscles(model: mujoco.MjModel, names: Sequence[str] | None = None) -> MuscleSet:
    """The muscles named (in that order), or every muscle actuator of ``model`` (in id order).

    Raises ``ValueError`` for a name that is no actuator, an actuator without a muscle gain
    (its ``gainprm`` holds no length range), a model without muscles, or a muscle whose
    ``lengthrange`` or ``range`` is empty (MuJoCo computes ``lengthrange`` for muscles when
    the model is compiled unless ``<compiler><lengthrange mode="none"/>``).
    """
    muscle = is_muscle(model)
    if names is None:
        ids = np.flatnonzero(muscle)
        if ids.size == 0:
            raise ValueError(
                f"the model has no muscle actuators: none of its {model.nu} actuators has "
                "muscle dynamics or a muscle gain (MJCF <muscle>, or <general> with "
                "gaintype=\"muscle\"). Spindle afferents need muscles, as in "
                "models/elbow.xml or myo-sim's models; motor-driven models such as "
                "Gymnasium's Humanoid-v5 or Ant-v5 have none (docs/wrapper.md)")
    else:
        if isinstance(names, str):
            names = [names]
        ids_list = []
        for name in names:
            i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, str(name))
            if i < 0:
                raise ValueError(f"muscles: {name!r} is not an actuator of the model")
            if model.actuator_gaintype[i] != mujoco.mjtGain.mjGAIN_MUSCLE:
                raise ValueError(f"muscles: actuator {name!r} has no muscle gain, so no "
                                 "normalised length (gainprm range, lengthrange); only "
                                 "muscle actuators (MJCF <muscle>, or <general> with "
                                 "gaintype=\"muscle\") can be named")
            ids_list.append(i)
        if not ids_list:
            raise ValueError("muscles is empty; pass None for every muscle actuator")
        if len(set(ids_list)) != len(ids_list):
            raise ValueError(f"muscles={list(names)!r} names an actuator twice")
        ids = np.array(ids_list, dtype=int)
    lr = np.asarray(model.actuator_lengthrange[ids], dtype=float)
    r = np.asarray(model.actuator_gainprm[ids, :2], dtype=float)
    names_out = tuple(model.actuator(int(i)).name for i in ids)
    for j, name in enumerate(names_out):
        if not (lr[j, 1] > lr[j, 0] and r[j, 1] > r[j, 0]):
            raise ValueError(
                f"muscle {name!r}: lengthrange {lr[j].tolist()} m and range {r[j].tolist()} "
                "must both be increasing intervals to normalise its length")
    return MuscleSet(
        names=names_out, ids=ids, optimal_length_m=(lr[:, 1] - lr[:, 0]) / (r[:, 1] - r[:, 0]),
        lengthrange_low_m=lr[:, 0].copy(), range_low_L0=r[:, 0].copy(),
        range_high_L0=r[:, 1].copy(),
        gear=np.array(model.actuator_gear[ids, 0], dtype=float))


class ActuatorKinematics:
    """Actuator lengths and velocities of any state, on a scratch ``MjData``.

    Args:
        model: the MuJoCo model.
        ids: actuator ids (M,).
    """

    def __init__(self, model: mujoco.MjModel, ids: np.ndarray) -> None:
        self.model = model
        self.ids = np.asarray(ids, dtype=int)
        self.scratch = mujoco.MjData(model)
        self._moment = np.zeros((model.nu, model.nv))

    def __getstate__(self) -> dict:
        # the scratch data holds nothing between calls (compute sets every input it reads)
        # and pickles as the model's whole arena (41 MB on myo-sim's elbow): made anew
        return {k: v for k, v in self.__dict__.items() if k != "scratch"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.scratch = mujoco.MjData(self.model)

    def compute(self, qpos: np.ndarray, qvel: np.ndarray,
                mocap_pos: np.ndarray | None = None, mocap_quat: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """(length_m, velocity_m_s), each (M,), at the state (qpos, qvel) (and mocap poses)."""
        m, d = self.model, self.scratch
        d.qpos[:] = qpos
        d.qvel[:] = qvel
        if m.nmocap and mocap_pos is not None:
            d.mocap_pos[:] = mocap_pos
            d.mocap_quat[:] = mocap_quat
        # mj_fwdPosition's stages that tendons and transmissions need (no collision, no
        # inertia): about a fifth of its cost on the 54-muscle legs
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_tendon(m, d)
        mujoco.mj_transmission(m, d)
        return d.actuator_length[self.ids], self._velocity(qvel)

    def forces(self, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, ctrl: np.ndarray,
               mocap_pos: np.ndarray | None = None, mocap_quat: np.ndarray | None = None
               ) -> np.ndarray:
        """``actuator_force`` (MuJoCo's sign: a muscle pulling is negative) of every
        actuator, (nu,), at the state (qpos, qvel, act) under ``ctrl``: the stages of
        ``mj_forward`` that the force needs (:meth:`compute`, the actuator velocities, then
        MuJoCo's own ``mj_fwdActuation``), so it equals what ``mj_forward`` gives there."""
        return self._state(qpos, qvel, act, ctrl, mocap_pos, mocap_quat)[2].copy()

    def state_of_data(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(length_m, velocity_m_s, actuator_force) of the actuators ``ids``, (M,) each, at
        the state held in ``data`` (which is not modified), in one pass (:meth:`forces`)."""
        length, velocity, force = self._state(data.qpos, data.qvel, data.act, data.ctrl,
                                              data.mocap_pos, data.mocap_quat)
        return length, velocity, force[self.ids]

    def _state(self, qpos, qvel, act, ctrl, mocap_pos, mocap_quat):
        """:meth:`compute`'s (length, velocity) of ``ids`` and the scratch's actuator_force
        of every actuator (a view) after ``mj_fwdActuation`` there."""
        d = self.scratch
        length, velocity = self.compute(qpos, qvel, mocap_pos, mocap_quat)
        # compute left every actuator's velocity in the scratch (mj_fwdActuation reads it)
        d.act[:] = act
        d.ctrl[:] = ctrl
        mujoco.mj_fwdActuation(self.model, d)
        return length, velocity, d.actuator_force

    def of_data(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`compute` at the state held in ``data`` (which is not modified)."""
        return self.compute(data.qpos, data.qvel, data.mocap_pos, data.mocap_quat)

    def _velocity(self, qvel: np.ndarray) -> np.ndarray:
        # actuator_velocity = moment . qvel; the moment is stored sparse, and one dense
        # product beats gathering the rows in numpy (5 + 2 us against 60 us, 54-muscle legs);
        # every actuator's, into the scratch, where mj_fwdActuation finds it (forces)
        d = self.scratch
        mujoco.mju_sparse2dense(self._moment, d.actuator_moment, d.moment_rownnz,
                                d.moment_rowadr, d.moment_colind)
        np.matmul(self._moment, qvel, out=d.actuator_velocity)
        return d.actuator_velocity[self.ids]


def model_and_data(env: object) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """The MuJoCo ``model`` and ``data`` of an env's ``unwrapped`` (Gymnasium's MuJoCo envs
    and ours: ``.model``/``.data``; MyoSuite: ``.sim.model``/``.sim.data``)."""
    base = getattr(env, "unwrapped", env)
    for holder in (base, getattr(base, "sim", None)):
        model, data = getattr(holder, "model", None), getattr(holder, "data", None)
        if isinstance(model, mujoco.MjModel) and isinstance(data, mujoco.MjData):
            return model, data
    raise ValueError(
        f"{type(base).__name__} exposes no MuJoCo model and data: the wrapper needs "
        "env.unwrapped.model (mujoco.MjModel) and env.unwrapped.data (mujoco.MjData), or "
        "env.unwrapped.sim.model / .sim.data")
