"""The muscle lengths after every physics step of an env step: recorded, or a Hermite curve.

A wrapper sees the env step, not the physics steps inside it. Two sources of the lengths in
between, chosen per env (``substep_source``):

- ``"frames"``: the env's physics stepping is wrapped so that each physics step is recorded.
  For Gymnasium's ``MujocoEnv`` (``do_simulation`` -> ``_step_mujoco_simulation``, not
  overridden by the env) the wrapper puts its own ``_step_mujoco_simulation`` on the
  instance: the same ``mj_step`` calls one by one (``mj_step(nstep=n)`` is that loop) and
  the same ``mj_rnePostConstraint``, reading after each call ``actuator_length`` and
  ``actuator_velocity``, which ``mj_step`` computed at the step's *start* (so the physics and
  the env's own data are bit-for-bit what they were). The state after the last step comes
  from :class:`~proprio_env.wrappers.muscles.ActuatorKinematics` on a scratch ``MjData``,
  or, with ``lag_physics_step``, is the next env step's first record (the afferents then
  describe the state one physics step before the env's; see :func:`step_knots`).
  Not with the RK4 integrator (its last stage leaves intermediate values in those fields).
  MyoSuite 3 (``MyoGymnasiumEnv._step_physics``: ``mj_step(nstep=frame_skip)`` then
  ``mj_forward``, not overridden by the task) is hooked the same way: its own
  ``_step_physics`` replaced on the instance by the loop of single ``mj_step`` calls and the
  same ``mj_forward``; since MyoSuite's data is then current, the state after the last step
  is read from it (no scratch kinematics).
- ``"hermite"``: for any other env (ours, older MyoSuite's ``sim.advance``): the cubic Hermite
  curve between the lengths and velocities at the ends of the env step, sampled at the
  physics step's times. On the elbow at 50 Hz it differs from the recorded lengths by up to
  the figure in ``docs/wrapper.md``.

``"auto"`` (default) takes ``"frames"`` where it can, else ``"hermite"``.

One :class:`PhysicsHook` per env instance does the recording for every wrapper on that env
(wrappers stacked with different muscles each get every physics step); a copy of the env
re-binds it to the copy's data. An env step longer than ``max_interval_s``
(:data:`MAX_INTERVAL_S`) restarts the wrappers' spindles (:func:`check_max_interval`), and
each recorder keeps at most the records of one such interval.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import mujoco
import numpy as np

from spindle.substeps import hermite_curve

SUBSTEP_SOURCES = ("auto", "frames", "hermite")


MYOSUITE_BASE = ("myosuite.envs.gymnasium_env", "MyoGymnasiumEnv")
"""Module and name of MyoSuite 3's env base class, whose ``_step_physics`` can be hooked
(matched by name: this package never imports MyoSuite)."""


def _myosuite_base(env: Any) -> type | None:
    for cls in type(env).__mro__:
        if (cls.__module__, cls.__name__) == MYOSUITE_BASE:
            return cls
    return None


def hook_kind(env: Any) -> tuple[str | None, str | None]:
    """(``"gymnasium"`` or ``"myosuite"``, None) if the physics steps of ``env`` (an
    ``unwrapped`` env) can be recorded, else (None, why not)."""
    model = getattr(env, "model", None)
    if isinstance(model, mujoco.MjModel) and \
            model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4:
        return None, "the RK4 integrator leaves intermediate values in actuator_length"
    base = _myosuite_base(env)
    if base is not None:
        if type(env)._step_physics is not base._step_physics:
            return None, f"{type(env).__name__} overrides MyoSuite's _step_physics"
        if not isinstance(getattr(env, "frame_skip", None), int):
            return None, f"{type(env).__name__} has no integer frame_skip"
        return _unless_replaced(env, "myosuite")
    try:
        from gymnasium.envs.mujoco.mujoco_env import MujocoEnv
    except ImportError as exc:  # gymnasium[mujoco] needs imageio
        return None, f"gymnasium.envs.mujoco is not importable ({exc})"
    if not isinstance(env, MujocoEnv):
        return None, (f"{type(env).__name__} is not a gymnasium.envs.mujoco.MujocoEnv nor a "
                      "MyoSuite 3 MyoGymnasiumEnv")
    if type(env)._step_mujoco_simulation is not MujocoEnv._step_mujoco_simulation:
        return None, f"{type(env).__name__} overrides _step_mujoco_simulation"
    return _unless_replaced(env, "gymnasium")


def _unless_replaced(env: Any, kind: str) -> tuple[str | None, str | None]:
    """(kind, None), unless the env instance's physics stepping was replaced by something
    other than this package's hook (whose steps would then go unrecorded)."""
    name = HOOKED_METHODS[kind]
    if name in env.__dict__:
        hook = env.__dict__.get(HOOK_ATTRIBUTE)
        if not (isinstance(hook, PhysicsHook) and hook.installed()):
            return None, f"the env instance's {name} was replaced by {env.__dict__[name]!r}"
    return kind, None


def frames_hook_reason(env: Any) -> str | None:
    """``None`` if the physics steps of ``env`` (an ``unwrapped`` env) can be recorded, else
    why not."""
    return hook_kind(env)[1]


HOOK_ATTRIBUTE = "_proprio_physics_hook"
"""Where an env instance keeps its :class:`PhysicsHook` (in its ``__dict__``), so that every
wrapper on that env shares the one hook."""

HOOKED_METHODS = {"gymnasium": "_step_mujoco_simulation", "myosuite": "_step_physics"}

DEFAULT_MAX_RECORDS = 4096
"""Records a :class:`FrameRecorder` keeps when no limit is given (the wrappers pass theirs,
from ``max_interval_s``)."""

_CHUNK_FRAMES = 1024
"""Physics steps recorded per pass of the hook's loop: bounds its staging buffers whatever
``n_frames`` the env asks for."""


class PhysicsHook:
    """The one replacement of an env instance's physics stepping, shared by every
    :class:`FrameRecorder` on that env (two wrappers with different ``muscles=`` on one env:
    both record every physics step).

    It makes the env's own ``mj_step`` calls one at a time (``mj_step(nstep=n)`` is that
    loop) and copies each step's ``actuator_length`` / ``actuator_velocity`` (every
    actuator) into each recorder. It keeps views of those two arrays of the env's
    ``MjData``; a copy of the env (``copy.deepcopy``, pickle) re-binds them to the copy's
    data (:meth:`__setstate__`), so the copy records its own physics, not frozen arrays.
    """

    def __init__(self, env: Any, kind: str, model: Any, data: Any) -> None:
        self.env, self.kind, self.model, self.data = env, kind, model, data
        self.recorders: list[FrameRecorder] = []
        self.end_time = float("nan")  # MyoSuite: data.time after its last mj_forward
        self._bind()
        env.__dict__[HOOK_ATTRIBUTE] = self
        setattr(env, HOOKED_METHODS[kind],
                self._step if kind == "gymnasium" else self._step_physics)

    @classmethod
    def of(cls, env: Any, kind: str, model: Any, data: Any) -> PhysicsHook:
        """The env's installed hook, or a new one installed."""
        hook = env.__dict__.get(HOOK_ATTRIBUTE)
        if isinstance(hook, cls) and hook.installed():
            return hook
        return cls(env, kind, model, data)

    def _bind(self) -> None:
        self._length_view = self.data.actuator_length
        self._velocity_view = self.data.actuator_velocity
        self._force_view = self.data.actuator_force
        self._staging(16)

    def _staging(self, rows: int) -> None:
        nu = self._length_view.size
        self._lengths, self._velocities, self._forces = (np.empty((rows, nu))
                                                         for _ in range(3))

    def __getstate__(self) -> dict[str, Any]:
        # views of MjData arrays would be copied as frozen arrays: rebound on load instead
        return {k: v for k, v in self.__dict__.items()
                if k not in ("_length_view", "_velocity_view", "_force_view", "_lengths",
                             "_velocities", "_forces")}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._bind()

    def installed(self) -> bool:
        """Whether the env still steps its physics through this hook."""
        method = self.env.__dict__.get(HOOKED_METHODS[self.kind])
        return getattr(method, "__self__", None) is self

    def _record_steps(self, n_frames: int) -> None:
        model, data = self.model, self.data
        step = mujoco.mj_step
        length_now, velocity_now = self._length_view, self._velocity_view
        force_now = self._force_view
        if self._lengths.shape[0] < min(n_frames, _CHUNK_FRAMES):
            self._staging(min(n_frames, _CHUNK_FRAMES))
        lengths, velocities, forces = self._lengths, self._velocities, self._forces
        timestep = float(model.opt.timestep)
        while n_frames > 0:
            n = min(n_frames, _CHUNK_FRAMES)
            # each step's start time as mj_step advances it (time += timestep, a left fold:
            # the same doubles), not read back per step: reading data.time cost as much as
            # 2 % of the legs' physics (and folded in place: np.r_ was 4 us a legs env step)
            times = np.full(n, timestep)
            times[0] = float(data.time)
            np.add.accumulate(times, out=times)
            for k in range(n):
                step(model, data)
                lengths[k] = length_now
                velocities[k] = velocity_now
                forces[k] = force_now
            for recorder in self.recorders:
                recorder.append(times, lengths[:n], velocities[:n], forces[:n])
            n_frames -= n

    def _step(self, ctrl, n_frames) -> None:
        self.data.ctrl[:] = ctrl
        self._record_steps(n_frames)
        mujoco.mj_rnePostConstraint(self.model, self.data)

    def _step_physics(self, nstep: int | None = None) -> None:
        self._record_steps(self.env.frame_skip if nstep is None else nstep)
        mujoco.mj_forward(self.model, self.data)
        self.end_time = float(self.data.time)

    def detach(self, recorder: FrameRecorder) -> None:
        """Stop feeding ``recorder``; the last one out restores the env."""
        self.recorders = [r for r in self.recorders if r is not recorder]
        if not self.recorders and self.installed():
            self.env.__dict__.pop(HOOKED_METHODS[self.kind], None)
            self.env.__dict__.pop(HOOK_ATTRIBUTE, None)


class FrameRecorder:
    """Records (time, actuator length, velocity, force) at the start of every physics step
    of a
    Gymnasium ``MujocoEnv`` or a MyoSuite 3 env (see the module docstring), through the
    env's one :class:`PhysicsHook`; :meth:`remove` restores the env once no recorder is
    left.

    Args:
        env: the ``unwrapped`` env.
        ids: the actuators :meth:`current` reads.
        model, data: the env's ``MjModel`` / ``MjData`` (default ``env.model`` /
            ``env.data``).
        max_records: the most records kept between two :meth:`take` calls: beyond it the
            oldest are dropped (counted in :attr:`dropped`), so that an env stepped for long
            without its wrapper (a user stepping ``env.unwrapped``) cannot fill memory. The
            wrappers pass one more than an interval of ``max_interval_s`` holds: a step that
            drops records restarts its spindles anyway.
    """

    def __init__(self, env: Any, ids: np.ndarray, model: Any = None, data: Any = None,
                 max_records: int = DEFAULT_MAX_RECORDS) -> None:
        kind, reason = hook_kind(env)
        if reason is not None:
            raise ValueError(f"substep_source='frames' is not possible here: {reason}")
        self.kind = kind
        self.max_records = int(max_records)
        if self.max_records < 2:
            raise ValueError(f"max_records={max_records!r} must be >= 2")
        self.hook = PhysicsHook.of(env, kind, env.model if model is None else model,
                                   env.data if data is None else data)
        self.ids = np.asarray(ids, dtype=int)
        self.dropped = 0
        self._count = 0
        nu = self.hook.data.actuator_length.size
        self._times, self._lengths, self._velocities, self._forces = \
            np.empty(16), np.empty((16, nu)), np.empty((16, nu)), np.empty((16, nu))
        self.hook.recorders.append(self)

    @property
    def data(self) -> Any:
        return self.hook.data

    def installed(self) -> bool:
        """Whether this recorder still gets the env's physics steps."""
        return self.hook.installed() and self in self.hook.recorders  # (no __eq__: identity)

    def append(self, times: np.ndarray, lengths: np.ndarray, velocities: np.ndarray,
               forces: np.ndarray) -> None:
        """Add F records (called by the hook), keeping the newest :attr:`max_records`."""
        n = times.size
        if self._count + n > self.max_records:
            keep = max(0, self.max_records - n)
            drop = self._count - keep
            if drop > 0:
                self.dropped += drop
                for a in (self._times, self._lengths, self._velocities, self._forces):
                    a[:keep] = a[drop:self._count]
                self._count = keep
            if n > self.max_records:
                self.dropped += n - self.max_records
                times, lengths, velocities, forces = (
                    a[-self.max_records:] for a in (times, lengths, velocities, forces))
                n = self.max_records
        start, end = self._count, self._count + n
        if end > self._times.size:
            self._grow(min(self.max_records, 2 * end))
        self._times[start:end] = times
        self._lengths[start:end] = lengths
        self._velocities[start:end] = velocities
        self._forces[start:end] = forces
        self._count = end

    def _grow(self, capacity: int) -> None:
        count = self._count
        for name in ("_times", "_lengths", "_velocities", "_forces"):
            old = getattr(self, name)
            new = np.empty((capacity, *old.shape[1:]))
            new[:count] = old[:count]
            setattr(self, name, new)

    def current(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(length m, velocity m/s, actuator force N) of the env's current state if its data
        holds them (MyoSuite, right after its physics steps), else None."""
        data = self.hook.data
        if self.hook.end_time == data.time:
            return (data.actuator_length[self.ids].copy(),
                    data.actuator_velocity[self.ids].copy(),
                    data.actuator_force[self.ids].copy())
        return None

    def take_all(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The records since the last call: times (F,), lengths (F, nu) m, velocities (F, nu)
        m/s and forces (F, nu) (MuJoCo's ``actuator_force``) of every actuator, each at the
        start of a physics step (``mj_step`` computes the force there, as the lengths). Views
        of the recorder's buffers, valid until its next physics step (the wrappers gather
        them at once)."""
        count, self._count = self._count, 0
        return (self._times[:count], self._lengths[:count], self._velocities[:count],
                self._forces[:count])

    def take(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`take_all` without the forces: (times, lengths, velocities)."""
        return self.take_all()[:3]

    def remove(self) -> None:
        self.hook.detach(self)


def hermite_knots(t0: np.ndarray, L0: np.ndarray, V0: np.ndarray, t1: np.ndarray,
                  L1: np.ndarray, V1: np.ndarray, K: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K equally spaced knots (times (K, n), lengths and slopes (K, n, M)) on the cubic
    Hermite curve from (L0, V0) at t0 to (L1, V1) at t1 (rows n, muscles M); the last is
    (L1, V1) itself. Between two such knots, the Hermite curve through them and their slopes
    is the same cubic, so the spindles follow the one curve."""
    dt = (t1 - t0)[:, None]
    s = np.arange(1, K + 1) / K
    times = t0[None, :] + s[:, None] * (t1 - t0)[None, :]
    lengths = np.stack([hermite_curve(si, L0, L1, [(V0 * dt, V1 * dt)], 1.0) for si in s])
    s2 = s[:, None, None]
    # d/dt of the curve: the derivatives of the cubic Hermite basis over dt
    slopes = ((6 * s2 * s2 - 6 * s2) * (L0 - L1)[None] / dt[None]
              + (3 * s2 * s2 - 4 * s2 + 1) * V0[None] + (3 * s2 * s2 - 2 * s2) * V1[None])
    lengths[-1], slopes[-1] = L1, V1
    return times, lengths, slopes


MAX_INTERVAL_S = 1.0
"""Default longest env step (s) over which the wrappers carry their spindles on; a longer one
(a clock set forward by hand, a reset that moves time, an env stepped for long without its
wrapper) restarts them at rest at the env's state, counted in ``restarts``: the work of a
step stays at most ``max_interval_s`` / the physics timestep knots (:func:`check_max_interval`)."""


def check_max_interval(max_interval_s: object, timestep_s: float, step_s: float,
                       env_dt_s: object = None) -> float:
    """``max_interval_s`` as a float; ``ValueError`` naming it unless it is a real number
    (not a bool, string or complex) at least one physics step (``timestep_s``) and the env
    step (``env_dt_s``, when the env tells it: its steps would all restart), and its knots'
    spindle sub-steps of at most ``step_s`` stay within :data:`spindle.simulation.MAX_SUBSTEPS`
    (the bound on one interval's work that ``spindle.simulate`` applies)."""
    from spindle.simulation import MAX_SUBSTEPS
    from spindle.substeps import substeps

    if isinstance(max_interval_s, bool | np.bool_) or not isinstance(
            max_interval_s, numbers.Real):
        raise ValueError(f"max_interval_s={max_interval_s!r} must be a real number of seconds")
    value = float(max_interval_s)
    if not (math.isfinite(value) and value >= timestep_s):
        raise ValueError(f"max_interval_s={max_interval_s!r} must be finite and at least the "
                         f"physics timestep {timestep_s!r} s")
    if isinstance(env_dt_s, numbers.Real) and math.isfinite(env_dt_s) and env_dt_s > value:
        raise ValueError(f"max_interval_s={max_interval_s!r} is shorter than the env step "
                         f"{float(env_dt_s)!r} s: every step would restart the spindles")
    # knots: one per physics step of the interval, and one more when lagging
    work = (math.ceil(value / timestep_s * (1 - 1e-12)) + 1) * substeps(timestep_s, step_s)
    if work > MAX_SUBSTEPS:
        raise ValueError(f"max_interval_s={max_interval_s!r} allows {work} spindle sub-steps "
                         f"per env step, above the limit MAX_SUBSTEPS = {MAX_SUBSTEPS}")
    return value


class EnvTap:
    """What the wrappers read from one env: its muscles' normalised state now, and the
    records of its last physics steps.

    Args:
        env: the env (its ``unwrapped`` is used).
        muscles: the muscle set (:func:`~proprio_env.wrappers.muscles.find_muscles`).
        substep_source: one of :data:`SUBSTEP_SOURCES`.
        lag_physics_step: end each env step's knots at the last recorded physics step (the
            state one physics step before the env's), not at the env's state: no kinematics
            per env step (see :func:`step_knots`). Needs the recorded frames.
        max_interval_s: the wrappers' restart interval; the recorder keeps the records of
            one such interval and one more.
    """

    def __init__(self, env: Any, muscles: Any, substep_source: str = "auto",
                 lag_physics_step: bool = False, max_interval_s: float = MAX_INTERVAL_S
                 ) -> None:
        from proprio_env.wrappers.muscles import ActuatorKinematics, model_and_data

        if substep_source not in SUBSTEP_SOURCES:
            raise ValueError(f"substep_source={substep_source!r} is not one of "
                             f"{SUBSTEP_SOURCES}")
        self.base = env.unwrapped
        self.model, self.data = model_and_data(self.base)
        self.muscles = muscles
        self.kinematics = ActuatorKinematics(self.model, muscles.ids)
        self.timestep_s = float(self.model.opt.timestep)
        reason = frames_hook_reason(self.base)
        if substep_source == "frames" and reason is not None:
            raise ValueError(f"substep_source='frames' is not possible here: {reason}")
        self.max_records = math.ceil(max_interval_s / self.timestep_s) + 2
        self.recorder = (FrameRecorder(self.base, muscles.ids, self.model, self.data,
                                       self.max_records)
                         if substep_source != "hermite" and reason is None else None)
        self.substep_source = "frames" if self.recorder is not None else "hermite"
        self.why_hermite = reason if self.recorder is None else None
        if lag_physics_step and self.recorder is None:
            raise ValueError("lag_physics_step=True needs the recorded physics steps "
                             f"(substep_source 'frames'), not possible here: {reason}")
        self.lag_physics_step = bool(lag_physics_step)
        # the spindles' last knot is one physics step before the env's state when lagging
        self.interval_limit_s = float(max_interval_s) + (
            self.timestep_s if self.lag_physics_step else 0.0)
        self._dropped = 0
        self.final: tuple | None = None  # see freeze()
        # the actuator forces (F, nu) of the last records() (None without them): kept
        # beside the records, which stay (times, lengths, velocities)
        self.record_forces: np.ndarray | None = None

    def time(self) -> float:
        """The env's time (s); while frozen, the time of the frozen state."""
        return float(self.data.time) if self.final is None else self.final[0][0]

    def rest_time(self, t_s: float) -> float:
        """The time of the knot at which spindles reset at the env's time ``t_s`` rest: one
        physics step earlier when lagging, so that the next step's records (the first at
        ``t_s``) follow it at the physics step's interval, as after any other step."""
        return t_s - self.timestep_s if self.lag_physics_step else t_s

    def now(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(time s, normalised lengths L0, velocities L0/s) of the env's current state (while
        frozen: of the frozen one)."""
        return self.state_now()[:3]

    def state_now(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`now` and the tendon forces (N): the muscles' tension
        (:meth:`~proprio_env.wrappers.muscles.MuscleSet.tension_N`) that MuJoCo's
        ``mj_fwdActuation`` gives at that state (on a scratch ``MjData`` unless the env's
        data is current), in the same pass."""
        t, *raw = self.raw_state_now()
        return (t, *normalised(self.muscles, *raw))

    def raw_state_now(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`state_now` before the normalisation: (time s, actuator lengths m,
        velocities m/s, ``actuator_force``) of the muscles, fresh arrays (M,)."""
        if self.final is not None:
            return self.final[0]
        current = None if self.recorder is None else self.recorder.current()
        length, velocity, force = (self.kinematics.state_of_data(self.data)
                                   if current is None else current)
        return float(self.data.time), length, velocity, force

    def records(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The raw records since the last call (:meth:`FrameRecorder.take_all`); None without a
        recorder, when the env no longer steps through it (something replaced the hook), or
        when records were dropped (a longer interval than the recorder keeps). While
        frozen: the records up to the frozen state."""
        if self.final is not None:
            self.record_forces = self.final[2]
            return self.final[1]
        self.record_forces = None
        if self.recorder is None:
            return None
        *out, forces = self.recorder.take_all()
        dropped, self._dropped = self.recorder.dropped - self._dropped, self.recorder.dropped
        if not (self.recorder.installed() and dropped == 0):
            return None
        self.record_forces = forces
        return tuple(out)

    def freeze(self) -> None:
        """Keep the env's state now and its records (copied) as what :meth:`time`,
        :meth:`now` and :meth:`records` return until :meth:`thaw`: the end of an episode
        that the env is about to reset (a vector env's ``SAME_STEP`` autoreset)."""
        records = self.records()
        kept = None if records is None else tuple(a.copy() for a in records)
        forces = None if self.record_forces is None else self.record_forces.copy()
        self.final = (self.raw_state_now(), kept, forces)

    def thaw(self) -> None:
        """Read the env again; the records of whatever stepped since :meth:`freeze` (the
        reset) are dropped."""
        self.final = None
        self.records()

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.remove()


TIME_TOL_S = 1e-9
"""Times closer than this are the same physics step (sums of ``mj_step``'s dt)."""


def gather_records(records: list, rows: np.ndarray, muscles: Any, forces: list,
                   every_force: bool = True
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The raw records (:meth:`EnvTap.records`) and their forces
    (:attr:`EnvTap.record_forces`) of ``rows`` as arrays of the muscles' columns, still raw
    (:func:`normalised` makes them L0, L0/s and N): times (F, r), lengths m, velocities m/s
    and forces (F, r, M) (``every_force`` False: the last record's only, (1, r, M)); None
    unless every row has the same number F >= 1. One stack for all rows."""
    chosen = [(*records[i], forces[i]) if records[i] is not None else None for i in rows]
    if not chosen or any(r is None or r[3] is None for r in chosen):
        return None
    count = chosen[0][0].size
    if count == 0 or any(r[0].size != count for r in chosen):
        return None
    cols = muscles.columns
    if len(chosen) == 1:  # one env: views of its records, no copy (9 of 28 us on the legs)
        r = chosen[0]
        t, length, velocity = r[0][:, None], r[1][:, None, cols], r[2][:, None, cols]
        force = (r[3] if every_force else r[3][-1:])[:, None, cols]
    else:
        # np.array of the rows, then the muscles' columns of its (F, r, nu) view: half the
        # time of np.stack (4 stacks were 12 us of a legs env step)
        t = np.array([r[0] for r in chosen]).T
        length, velocity, force = (np.array([r[k] if k < 3 or every_force else r[k][-1:]
                                             for r in chosen]).transpose(1, 0, 2)[..., cols]
                                   for k in (1, 2, 3))
    return t, length, velocity, force


def normalised(muscles: Any, length_m: np.ndarray, velocity_m_s: np.ndarray,
               force: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw actuator lengths (m), velocities (m/s) and forces (MuJoCo's sign), (..., M), as
    normalised lengths (L0), velocities (L0/s) and tendon forces (N)."""
    return (muscles.length_L0(length_m), muscles.velocity_L0_s(velocity_m_s),
            muscles.tension_N(force))


def _stacked(states: list) -> tuple[np.ndarray, ...]:
    return tuple(np.array([x[k] for x in states]) for k in range(4))


def _raw_ends(taps: list, rows: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each row's env state now, raw (:meth:`EnvTap.raw_state_now`): times (1, r), lengths,
    velocities and forces (1, r, M), ready to follow the raw records."""
    if rows.size == 1:  # one env: its arrays with two new axes, no stack
        t, *raw = taps[rows[0]].raw_state_now()
        return (np.array([[t]]), *(a[None, None] for a in raw))
    return tuple(a[None] for a in _stacked([taps[i].raw_state_now() for i in rows]))


def _step_end(taps: list, records: list, rows: np.ndarray) -> tuple[np.ndarray, ...]:
    """The last knot of each row's env step, (r,) and (r, M) x 3 (lengths, velocities,
    forces): its env's state now, or, lagging, its last record (its env's state now if it
    has none)."""
    ends = []
    for i in rows:
        tap, r, f = taps[i], records[i], taps[i].record_forces
        if not tap.lag_physics_step or r is None or r[0].size == 0 or f is None:
            ends.append(tap.state_now())
        else:
            m = tap.muscles
            ends.append((float(r[0][-1]), m.length_L0(r[1][-1, m.ids]),
                         m.velocity_L0_s(r[2][-1, m.ids]), m.tension_N(f[-1, m.ids])))
    return _stacked(ends)


def _records_follow(t_first: np.ndarray, t_last: np.ndarray, timestep_s: float
                    ) -> tuple[int, bool]:
    """(1 if each row's first record is its previous knot itself, else 0; whether it is that
    knot or one physics step after it in every row), the rows' first record times and last
    knot times (r,) compared within :data:`TIME_TOL_S` and a few units in the last place (a
    clock far from 0, set forward by hand or after a long run, resolves its physics steps
    only to those)."""
    if t_last.size == 1 and math.isfinite(last := float(t_last[0])):
        # one env: the same comparisons on Python floats (math.ulp is np.spacing for a
        # finite non-negative float), not 8 numpy calls on one-element arrays (~40k of a
        # legs env step's ~1.7M added instructions, callgrind)
        first = float(t_first[0])
        tol = TIME_TOL_S + 4 * math.ulp(abs(last))
        drop = int(abs(first - last) <= tol)
        return drop, bool(drop) or abs((first - last) - timestep_s) <= tol
    first = t_first - t_last
    tol = TIME_TOL_S + 4 * np.spacing(np.abs(t_last))
    drop = int((np.abs(first) <= tol).all())
    return drop, bool(drop) or bool((np.abs(first - timestep_s) <= tol).all())


def step_knots(taps: list, records: list, t_prev: np.ndarray, L_prev: np.ndarray,
               V_prev: np.ndarray, moving: np.ndarray, F_prev: np.ndarray | None = None,
               every_force: bool = True
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    """The knots of one env step of n envs (``taps``, one per row, all alike): times (K, n),
    normalised lengths, velocities and tendon forces (N) (K, n, M), and ``"frames"`` or
    ``"hermite"``. ``every_force`` False: the recorded frames' forces only at the last knot,
    (1, n, M) (what the force readout keeps without the tendon organs; on myo-sim's legs
    the other knots' forces were 7 us of an env step's ~170 us).

    Args:
        taps: the envs' :class:`EnvTap`.
        records: each env's raw records of this step (:meth:`EnvTap.records`).
        t_prev, L_prev, V_prev: each row's previous knot, (n,) and (n, M); F_prev its
            forces (n, M) (the Hermite path draws the forces' line from them; default 0).
        moving: (n,) bool, the rows to advance. The others get copies of the first moving
            row's times (the bank holds them still).

    The recorded frames are used when every moving row has as many, and they line up with
    the previous knot the same way in every row: their first record is the previous knot
    itself (nothing moved the state in between; it is dropped), or one physics step after it
    (lagging). The env's state now follows them, unless lagging (then the last record is the
    step's last knot, and the state after the last physics step is the next env step's first
    record: every physics step's lengths are used exactly once). Otherwise the Hermite curve
    from the previous knot to the step's end, sampled every physics step, and the forces on
    the straight line between the step's ends (a wrapper sees no force in between).
    """
    rows = moving.nonzero()[0]  # (np.flatnonzero: three more Python calls; moving is 1-D)
    n, M = L_prev.shape
    F_prev = np.zeros((n, M)) if F_prev is None else F_prev
    lag, timestep_s = taps[0].lag_physics_step, taps[0].timestep_s
    stacked = gather_records(records, rows, taps[0].muscles,
                             [tap.record_forces for tap in taps], every_force)
    if stacked is not None:
        t_rec = stacked[0]
        drop, follows = _records_follow(t_rec[0], t_prev[rows], timestep_s)
        if follows and t_rec.shape[0] - drop + (not lag) >= 1:
            knots = [a[drop:] for a in stacked[:3]]
            forces = stacked[3][drop:] if every_force else stacked[3]
            if not lag:
                # the state now after the records, both raw: one normalisation of the
                # knots (two were 12 numpy calls of a legs env step)
                ends = _raw_ends(taps, rows)
                knots = [np.concatenate((a, e)) for a, e in zip(knots, ends[:3], strict=True)]
                forces = np.concatenate((forces, ends[3])) if every_force else ends[3]
            knots = [knots[0], *normalised(taps[0].muscles, *knots[1:], forces)]
            if rows.size == n:
                return (*knots, "frames")
            K = knots[0].shape[0]
            t, L, V, F = np.empty((K, n)), *(np.empty((K, n, M)) for _ in range(2)), \
                np.empty((knots[3].shape[0], n, M))
            t[:, rows], L[:, rows], V[:, rows], F[:, rows] = knots
            _fill_held(t, L, V, rows, moving)
            return t, L, V, F, "frames"
    t_end, L_end, V_end, F_end = (np.array(a, float) for a in (t_prev, L_prev, V_prev, F_prev))
    if rows.size:
        t_end[rows], L_end[rows], V_end[rows], F_end[rows] = _step_end(taps, records, rows)
    span = t_end[rows] - t_prev[rows]
    counts = np.maximum(1, np.rint(span / timestep_s)).astype(int)
    if rows.size and np.any(counts != counts[0]):
        raise ValueError(f"the envs advanced by different times {span.tolist()} s in one step")
    K = int(counts[0]) if rows.size else 1
    t, L, V = hermite_knots(t_prev, L_prev, V_prev, np.where(moving, t_end, t_prev + 1.0),
                            L_end, V_end, K)
    s = (np.arange(1, K + 1) / K)[:, None, None]
    F = F_prev[None] + s * (F_end - F_prev)[None]
    F[-1] = F_end
    _fill_held(t, L, V, rows, moving)
    return t, L, V, F, "hermite"


def _fill_held(t, L, V, rows, moving) -> None:
    held = np.flatnonzero(~moving)
    if held.size and rows.size:
        t[:, held] = t[:, rows[:1]]
