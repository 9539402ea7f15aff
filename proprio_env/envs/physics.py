"""The physics of one env step for one or many envs: ``mujoco.rollout`` over full-physics
states, the tendon lengths recorded by sensors.

Both the single env (``n = 1``, its own ``MjData`` as the scratch data) and the vector env
(``n`` states, one scratch ``MjData`` per thread) step through :class:`PhysicsBatch`, so a
sub-env of the vector env and a single env fed the same actions go through the same
arithmetic. Measured on the 2-core dev machine (64 envs, 10 steps of 2 ms per env step, env
steps/s): a Python loop of ``mj_step`` recording time, angle and tendon lengths 6,000; the
same over two Python threads 6,300; ``mujoco.rollout`` on the calling thread 10,800 (the
``mj_step``-only limit 8,400-10,600 in the same run); rollout's pool of 2 threads 15,000.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout

from proprio_env.body.model import MUSCLES
from proprio_env.wrappers.muscles import ActuatorKinematics

STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS
"""What a stored env state holds (time, qpos, qvel, act, mocap, userdata, plugin state)."""
_CTRL = int(mujoco.mjtState.mjSTATE_CTRL.value)


def load_sensed_model(model_file: str | Path, forces: bool = False) -> mujoco.MjModel:
    """The MJCF at ``model_file`` with a ``tendonpos`` sensor per muscle (in MUSCLES order)
    appended at load time, and with ``forces`` an ``actuatorfrc`` sensor per actuator (in
    actuator order, after them): the file on disk, whose sha256 keys the length fits, is not
    changed, and sensors do not change the dynamics."""
    spec = mujoco.MjSpec.from_file(str(model_file))
    for name in MUSCLES:
        spec.add_sensor(name=f"_proprio_len_{name}", type=mujoco.mjtSensor.mjSENS_TENDONPOS,
                        objtype=mujoco.mjtObj.mjOBJ_TENDON, objname=name)
    if forces:
        for actuator in spec.actuators:
            spec.add_sensor(name=f"_proprio_frc_{actuator.name}",
                            type=mujoco.mjtSensor.mjSENS_ACTUATORFRC,
                            objtype=mujoco.mjtObj.mjOBJ_ACTUATOR, objname=actuator.name)
    return spec.compile()


def check_threads(num_threads: object) -> int:
    """``num_threads`` as an int >= 1 (1: physics on the calling thread)."""
    if isinstance(num_threads, bool) or not isinstance(num_threads, int | np.integer) or (
            int(num_threads) < 1):
        raise ValueError(f"num_threads={num_threads!r} must be an integer >= 1")
    return int(num_threads)


class PhysicsBatch:
    """The states of ``n`` copies of one model and the stepping of all of them.

    Args:
        model: the model (with the tendon sensors of :func:`load_sensed_model`).
        n: number of envs.
        frames: physics steps per env step.
        num_threads: 1 steps on the calling thread; more uses rollout's thread pool.
        scratch: the ``MjData`` to step in (``n == 1`` and one thread: the single env's
            own data, which then holds the state after each step); default: new ones.
        qadr, vadr: the elbow joint's qpos / qvel addresses.
    """

    def __init__(self, model: mujoco.MjModel, n: int, frames: int, num_threads: int = 1,
                 scratch: list[mujoco.MjData] | None = None, qadr: int = 0,
                 vadr: int = 0) -> None:
        self.model, self.n, self.frames = model, n, frames
        self.num_threads = check_threads(num_threads)
        nthread = 0 if self.num_threads == 1 else self.num_threads
        self._runner = rollout.Rollout(nthread=nthread)
        self.scratch = scratch if scratch is not None else [
            mujoco.MjData(model) for _ in range(max(1, nthread))]
        self._models = [model] * n
        nstate = mujoco.mj_stateSize(model, STATE_SPEC)
        self.state = np.zeros((n, nstate))
        self.ctrl = np.zeros((n, model.nu))
        self._control = np.zeros((n, frames, model.nu))
        self._warmstart = np.zeros((n, model.nv))
        self.states_out = np.zeros((n, frames, nstate))
        self.sensors_out = np.zeros((n, frames, model.nsensordata))
        self.qpos_index = 1 + qadr
        self.qvel_index = 1 + model.nq + vadr
        # the elbow's (angle, velocity) columns of a state as a slice: a view, where an
        # index array (fancy indexing) costs a copy and ~5k instructions per step
        self.qpos_qvel = slice(self.qpos_index, self.qvel_index + 1,
                               self.qvel_index - self.qpos_index)
        sensor0 = model.sensor(f"_proprio_len_{MUSCLES[0]}").id
        self.sensor_adr = int(model.sensor_adr[sensor0])
        self._tendon_ids = np.array([model.tendon(name).id for name in MUSCLES])
        self.force_adr = None  # the actuator-force sensors' address, if the model has them
        if model.nu and mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR,
                                          f"_proprio_frc_{model.actuator(0).name}") >= 0:
            self.force_adr = int(model.sensor_adr[model.sensor(
                f"_proprio_frc_{model.actuator(0).name}").id])
            self._kinematics = ActuatorKinematics(model, np.arange(model.nu))

    def close(self) -> None:
        """Stop the thread pool (stepping afterwards raises RuntimeError)."""
        if self._runner is not None:
            self._runner.close()
            self._runner = None

    def store(self, i: int, data: mujoco.MjData) -> None:
        """Env ``i``'s state and controls from ``data`` (after a reset)."""
        mujoco.mj_getState(self.model, data, self.state[i], STATE_SPEC)
        self.ctrl[i] = data.ctrl

    def load(self, i: int, data: mujoco.MjData) -> None:
        """Env ``i``'s state into ``data`` and the derived quantities (to render it)."""
        mujoco.mj_setState(self.model, data, self.state[i], STATE_SPEC)
        data.ctrl[:] = self.ctrl[i]
        mujoco.mj_forward(self.model, data)

    def step(self) -> None:
        """Advance every env by ``frames`` physics steps under its controls ``ctrl``; the
        states after each step land in ``states_out``, the sensors in ``sensors_out``
        (a tendon sensor after a step holds the length at the *start* of that step)."""
        if self._runner is None:
            raise RuntimeError("the physics is closed")
        self._control[:] = self.ctrl[:, None, :]
        # the warm start is zeroed at every env step so that an env's physics does not
        # depend on which scratch data (or thread) stepped it before
        self._runner.rollout(self._models, self.scratch, self.state, self._control,
                             control_spec=_CTRL, skip_checks=True, nstep=self.frames,
                             initial_warmstart=self._warmstart, state=self.states_out,
                             sensordata=self.sensors_out)
        self.state[:] = self.states_out[:, -1]

    def time_s(self) -> np.ndarray:
        """(n, frames) physics times after each step."""
        return self.states_out[:, :, 0]

    def angle_rad(self) -> np.ndarray:
        """(n, frames) elbow angles after each step."""
        return self.states_out[:, :, self.qpos_index]

    def tendon_lengths_m(self, data: mujoco.MjData | None = None) -> np.ndarray:
        """(n, frames, 2) muscle-tendon lengths after each step: the sensors give all but the
        last, which is computed on ``data`` (default the first scratch data) from each
        env's final position."""
        a = self.sensor_adr
        out = np.empty((self.n, self.frames, 2))
        out[:, :-1] = self.sensors_out[:, 1:, a:a + 2]
        data = self.scratch[0] if data is None else data
        m = self.model
        # MjData's views read once, not per env (a vector env of 64 spends ~25k instructions
        # per env in this loop; more views set up here would cost the single env)
        qpos, ten_length, nq = data.qpos, data.ten_length, m.nq
        for i in range(self.n):
            qpos[:] = self.state[i, 1:1 + nq]
            mujoco.mj_kinematics(m, data)
            mujoco.mj_tendon(m, data)
            out[i, -1] = ten_length[self._tendon_ids]
        return out

    def actuator_forces(self) -> np.ndarray:
        """(n, frames, nu) ``actuator_force`` (MuJoCo's sign) after each step (needs the
        model of ``load_sensed_model(..., forces=True)``): the sensors give all but the last
        (an ``actuatorfrc`` sensor after a step holds the force of the step's start state,
        i.e. of the state after the previous step), the last is computed from each env's final
        state and controls with MuJoCo's ``mj_fwdActuation`` on a scratch data
        (:meth:`~proprio_env.wrappers.muscles.ActuatorKinematics.forces`)."""
        a, nu, m = self.force_adr, self.model.nu, self.model
        out = np.empty((self.n, self.frames, nu))
        out[:, :-1] = self.sensors_out[:, 1:, a:a + nu]
        nq, nv, na = m.nq, m.nv, m.na
        for i in range(self.n):
            s = self.state[i]
            out[i, -1] = self._kinematics.forces(
                s[1:1 + nq], s[1 + nq:1 + nq + nv], s[1 + nq + nv:1 + nq + nv + na],
                self.ctrl[i])
        return out

    # -- pickling and copying: the thread pool is rebuilt ------------------------------------
    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_runner"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        nthread = 0 if self.num_threads == 1 else self.num_threads
        self._runner = rollout.Rollout(nthread=nthread)
