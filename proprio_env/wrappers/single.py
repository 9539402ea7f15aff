"""``SpindleAfferents``: Ia and II of every muscle of a MuJoCo env, appended to its observation."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from proprio_env import RATE_SCALE_PPS
from proprio_env.wrappers.capture import MAX_INTERVAL_S, EnvTap, check_max_interval, step_knots
from proprio_env.wrappers.forces import DEFAULT_AFFERENTS, ForceReadout, check_afferents
from proprio_env.wrappers.muscles import MuscleSet, find_muscles, model_and_data
from spindle.backends import DEFAULT_BACKEND
from spindle.chain.driver import (
    COUNTERS,
    ConstantFusimotor,
    SpindleDriver,
    TemplateFusimotor,
)
from spindle.core import SLEW_LIMIT_L0_S
from spindle.params import HUMAN, SpindleParams

OBSERVATION_MODES = ("box", "dict")
DICT_KEYS = {"ia": "spindle_ia", "ii": "spindle_ii", "ib": "tendon_ib"}
"""The Dict observation's key of each afferent."""


def check_rate_scale(rate_scale_pps: float) -> float:
    """``rate_scale_pps`` as a float; ``ValueError`` unless it is finite and > 0."""
    if not (np.isfinite(rate_scale_pps) and rate_scale_pps > 0):
        raise ValueError(f"rate_scale_pps={rate_scale_pps!r} must be finite and > 0")
    return float(rate_scale_pps)


def afferent_spaces(base: spaces.Space, n_muscles: int, mode: str,
                    afferents: tuple[str, ...] = DEFAULT_AFFERENTS) -> spaces.Space:
    """The observation space with the rates of ``afferents`` added: a Box concatenation
    (``"box"``, the env's space must be a 1-D Box) or a Dict (``"dict"``: the env's Dict with
    a key per afferent, :data:`DICT_KEYS`, or ``{"observation": the env's space, ...}``)."""
    if mode not in OBSERVATION_MODES:
        raise ValueError(f"observation={mode!r} is not one of {OBSERVATION_MODES}")
    width = len(afferents) * n_muscles
    if mode == "box":
        if not (isinstance(base, spaces.Box) and len(base.shape) == 1):
            raise ValueError(f"observation='box' needs a 1-D Box observation space, the env "
                             f"has {base}; pass observation='dict'")
        dtype = base.dtype
        low = np.concatenate((base.low, np.zeros(width, dtype=dtype)))
        high = np.concatenate((base.high, np.full(width, np.inf, dtype=dtype)))
        return spaces.Box(low, high, dtype=dtype)
    rate = spaces.Box(0.0, np.inf, shape=(n_muscles,), dtype=np.float64)
    keys = {DICT_KEYS[a]: rate for a in afferents}
    if isinstance(base, spaces.Dict):
        clash = set(keys) & set(base.spaces)
        if clash:
            raise ValueError(f"the env's Dict observation already has keys {sorted(clash)}")
        return spaces.Dict({**base.spaces, **keys})
    return spaces.Dict({"observation": base, **keys})


def add_afferents(obs: Any, rates: dict[str, np.ndarray], mode: str, scale: float,
                  dtype: Any = None) -> Any:
    """``obs`` with the ``rates`` (pps, by afferent name, in observation order) added (the
    last axis is the muscles; a leading env axis for a vector env)."""
    if mode == "box":
        parts = (np.asarray(obs), *(r / scale for r in rates.values()))
        return np.concatenate(parts, axis=-1).astype(dtype or np.asarray(obs).dtype)
    extra = {DICT_KEYS[name]: r / scale for name, r in rates.items()}
    if isinstance(obs, dict):
        return {**obs, **extra}
    return {"observation": obs, **extra}


def afferent_rates(bank: SpindleDriver, forces: ForceReadout, afferents: tuple[str, ...],
                   row: int | slice = slice(None)) -> dict[str, np.ndarray]:
    """The rates (pps) of ``afferents`` of row ``row`` (every row by default)."""
    source = {"ia": lambda: bank.ia_pps, "ii": lambda: bank.ii_pps,
              "ib": lambda: forces.ib_pps}
    return {name: source[name]()[row] for name in afferents}


def bank_info(bank: SpindleDriver, measured_L0: np.ndarray, source: str,
              row: int | None = None) -> dict[str, Any]:
    """The raw signals of a bank (row ``row``, or every row with a leading axis)."""
    pick = (lambda a: a[row].copy()) if row is not None else (lambda a: a.copy())
    info = {
        "spindle_ia_pps": pick(bank.ia_pps),
        "spindle_ii_pps": pick(bank.ii_pps),
        "spindle_length_L0": pick(bank.length_L0),
        "spindle_measured_length_L0": pick(measured_L0),
        "spindle_velocity_L0_s": pick(bank.velocity_L0_s),
        "spindle_gamma_static_pps": pick(bank.gamma_static_pps),
        "spindle_gamma_dynamic_pps": pick(bank.gamma_dynamic_pps),
    }
    for name in COUNTERS:
        info[f"spindle_{name}"] = pick(bank.counters[name])
    if row is not None:
        info["spindle_substep_source"] = source
        info["spindle_substeps_limited"] = bank.substeps_limited
        info["spindle_restarts"] = bank.restarts
    return info


class SpindleAfferents(gym.Wrapper):
    """Muscle-spindle Ia and II afferents (Mileusnic 2006) of every muscle of a MuJoCo env.

    Works on any env whose ``unwrapped`` has a MuJoCo ``model`` and ``data`` (Gymnasium's
    ``MujocoEnv`` subclasses, MyoSuite-style envs with ``sim.model``/``sim.data``, this
    project's elbow envs). Each muscle actuator's normalised fibre length and velocity come
    from MuJoCo's muscle model (:mod:`proprio_env.wrappers.muscles`); within each env step
    the spindles take 1 ms sub-steps along the lengths after every physics step
    (:mod:`proprio_env.wrappers.capture`); the rates are appended to the observation.

    Observation: the env's, then, for each of ``afferents`` in turn (default Ia then II;
    ``("ia", "ii", "ib")`` adds the tendon organs' Ib), its rate of each muscle, divided by
    ``rate_scale_pps`` (``observation="box"``: a Box concatenation, the env's space must be a
    1-D Box); or a Dict with keys ``"spindle_ia"``, ``"spindle_ii"``, ``"tendon_ib"`` (those
    chosen; ``observation="dict"``). Muscles are in :attr:`muscle_names` order (actuator ids
    unless ``muscles`` names them).

    ``info`` gains ``spindle_ia_pps``, ``spindle_ii_pps`` (M,) in pps;
    ``spindle_length_L0`` (as fed to the spindles: clamped to 0.5-1.5 L0, slew-limited) and
    ``spindle_measured_length_L0`` (MuJoCo's normalisation, unclamped); ``spindle_velocity_L0_s``;
    ``spindle_gamma_static_pps``, ``spindle_gamma_dynamic_pps``; per-muscle counters
    ``spindle_length_clamped``, ``spindle_slew_limited`` (since reset); and
    ``spindle_substep_source``, ``spindle_substeps_limited``, ``spindle_restarts``; and the
    force side (:mod:`proprio_env.wrappers.forces`): ``tendon_force_N`` (M,), each muscle's
    tendon tension from MuJoCo's ``actuator_force`` at the env's state, and with ``"ib"``
    ``tendon_ib_pps`` (M,) and the force rule's counts ``tendon_force_held`` (non-finite
    forces that held the previous one) and ``tendon_force_clamped`` (above 10^5 N).

    Reset: the spindles at equilibrium at the reset lengths with the drive there, the tendon
    organs at rest at the reset forces.

    Args:
        env: the env to wrap.
        muscles: actuator names to use (each with a muscle gain); ``None``: every muscle.
        params: spindle constants (default :data:`spindle.HUMAN`).
        fusimotor: :class:`~proprio_env.wrappers.ConstantFusimotor` (default: 85 pps static,
            100 pps dynamic) or :class:`~proprio_env.wrappers.TemplateFusimotor` (the seed
            paper's PI template and h/g per muscle).
        observation: ``"box"`` or ``"dict"``.
        rate_scale_pps: divisor of the rates in the observation.
        substep_source: ``"auto"``, ``"frames"`` or ``"hermite"`` (see
            :mod:`proprio_env.wrappers.capture`).
        method, step_s: the spindle integrator and its largest sub-step (default
            trapezoidal, 1 ms).
        max_speed_L0_s: the lengths' slew limit (L0/s).
        backend: the spindle core, ``"numpy"``, ``"c"`` (the C port's batch step, built on
            first use; needs a C compiler or a cached build) or ``"auto"`` (the default: C when
            it builds or loads here, else numpy; :func:`spindle.backends.resolve_backend`). Both
            give the same rates to ~1e-10 pps; C costs a fraction of numpy
            (``scripts/bench_wrapper.py``).
        lag_physics_step: the afferents describe the muscles one physics step before the
            env's state: each env step's spindles stop at its last physics step but one
            (whose lengths ``mj_step`` computed anyway) and take the last one at the start of
            the next env step. Every physics step's lengths are still used, exactly, once;
            this saves the end-of-step kinematics (on myo-sim's legs as much as a physics
            step, ``docs/wrapper.md``). Needs the recorded physics steps
            (``substep_source`` ``"frames"``). After a reset, the spindles rest at the reset
            lengths from one physics step before it. Default False: the env's state now.
        afferents: which rates go into the observation, in that order: names from
            ``("ia", "ii", "ib")`` (default ``("ia", "ii")``). Ib (Lin & Crago 2002 tendon
            organs, :mod:`spindle.tendon_organ`, human preset, the force scale from each
            muscle's maximum isometric force ``gainprm[2]``) is computed only when asked for;
            the forces are in ``info`` either way.
        max_interval_s: the longest env step (s) the spindles are carried through (default
            1 s). A longer one (the env's clock set forward, a reset inside ``step`` that
            moves time, the env stepped for long without the wrapper) restarts them at rest
            at the env's state, counted in ``spindle_restarts``, so that the work of a step
            is bounded. ``ValueError`` if it is shorter than a physics step or the env step,
            or needs more than ``spindle.simulation.MAX_SUBSTEPS`` spindle sub-steps.

    Copies (``copy.deepcopy``, ``pickle``) of a wrapped env continue bit for bit as the
    original would, on either backend. Several wrappers on one env share its recorded
    physics steps.

    Version history: v0 (first release); v0.1: ``backend``; v0.2: ``lag_physics_step``;
    v0.3: ``max_interval_s``, copies, wrappers stacked on one env; ``backend`` defaults to
    ``"auto"`` (was ``"numpy"``); v0.4: ``afferents`` (Ib), ``info["tendon_force_N"]``.
    """

    def __init__(self, env: gym.Env, muscles: Sequence[str] | None = None,
                 params: SpindleParams = HUMAN,
                 fusimotor: ConstantFusimotor | TemplateFusimotor | None = None,
                 observation: str = "box", rate_scale_pps: float = RATE_SCALE_PPS,
                 substep_source: str = "auto", method: str = "trapezoidal",
                 step_s: float | None = None, max_speed_L0_s: float = SLEW_LIMIT_L0_S,
                 backend: str = DEFAULT_BACKEND, lag_physics_step: bool = False,
                 max_interval_s: float = MAX_INTERVAL_S,
                 afferents: Sequence[str] = DEFAULT_AFFERENTS) -> None:
        super().__init__(env)
        model, _ = model_and_data(env)
        self.muscles: MuscleSet = find_muscles(model, muscles)
        self.afferents = check_afferents(afferents)
        self.rate_scale_pps = check_rate_scale(rate_scale_pps)
        self.observation_mode = observation
        self.observation_space = afferent_spaces(env.observation_space, self.muscles.n,
                                                 observation, self.afferents)
        bank = SpindleDriver(1, self.muscles.range_low_L0, self.muscles.range_high_L0,
                           params, fusimotor, method, step_s, max_speed_L0_s, backend)
        self.max_interval_s = check_max_interval(
            max_interval_s, float(model.opt.timestep), bank.step_s,
            getattr(env.unwrapped, "dt", None))
        self.forces = ForceReadout(model, self.muscles.ids, 1, "ib" in self.afferents,
                                   float(model.opt.timestep), bank.backend)
        self.tap = EnvTap(env, self.muscles, substep_source, lag_physics_step,
                          self.max_interval_s)
        self.bank = bank
        self._measured = np.ones((1, self.muscles.n))
        self._source = self.tap.substep_source
        self._started = False

    @property
    def muscle_names(self) -> tuple[str, ...]:
        return self.muscles.names

    @property
    def substep_source(self) -> str:
        """``"frames"`` or ``"hermite"``: how the lengths inside the last env step were
        obtained (after a reset: the source the next step will try, the recorded frames
        where the env could be hooked). A step whose records are missing or do not line up
        (the hook replaced, the clock set by hand) falls back to the Hermite curve and says
        so here and in ``info["spindle_substep_source"]``."""
        return self._source

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.tap.records()  # whatever the reset stepped belongs to no env step
        self._rest()
        self._source = self.tap.substep_source
        self._started = True
        return self._observation(obs), {**info, **self._info()}

    def step(self, action):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        obs, reward, terminated, truncated, info = self.env.step(action)
        records = [self.tap.records()]
        t_env = self.tap.time()
        t_prev = float(self.bank.t_s[0])
        if not (t_prev <= t_env <= t_prev + self.tap.interval_limit_s):
            # the env reset itself inside step (time ran back), or its clock jumped (set by
            # hand, a reset that moves it): start again at rest there
            self.bank.restarts += 1
            self._rest()
        elif t_env > t_prev:
            moving = np.ones(1, bool)
            t, L, V, F, self._source = step_knots([self.tap], records, self.bank.t_s,
                                                  self.bank.length_L0,
                                                  self.bank.velocity_L0_s, moving,
                                                  self.forces.force_N)
            self.bank.advance(t, L, V)
            self.forces.advance(F, moving)
            self._measured[0] = L[-1, 0]
        return (self._observation(obs), reward, terminated, truncated,
                {**info, **self._info()})

    def close(self) -> None:
        self.tap.close()
        super().close()

    def _rest(self) -> None:
        t, L, V, F = self.tap.state_now()
        self.bank.reset(None, np.array([self.tap.rest_time(t)]), L[None], V[None])
        self.forces.reset(np.zeros(1, int), F[None])
        self._measured[0] = L

    def _observation(self, obs):
        return add_afferents(obs, afferent_rates(self.bank, self.forces, self.afferents, 0),
                             self.observation_mode, self.rate_scale_pps,
                             getattr(self.observation_space, "dtype", None))

    def _info(self) -> dict[str, Any]:
        return {**bank_info(self.bank, self._measured, self._source, row=0),
                **self.forces.info(0)}
