"""Fault injection for the spindle-afferent wrappers: random actions on the elbow, with a
fault between steps, on both backends; the wrapper section of ``scripts/fault_soak.py``.

Targets, each on ``backend="numpy"`` and ``"c"``: ``SpindleAfferents`` on the bundled elbow
(``MuscleModelEnv``, recorded frames), the same with ``lag_physics_step``, and
``SpindleAfferentsVector`` over three sub-envs with ``SAME_STEP`` autoreset; episodes of
:data:`EPISODE_STEPS` steps. Before a step, with the fault probability, one of
:data:`WRAPPER_FAULTS`:

- ``clock_near``: the env's clock (one sub-env's for the vector) set forward by 1 ms-0.5 s,
  inside ``max_interval_s`` (bridged; a vector sub-env that moved unlike the others restarts);
- ``clock_far``: forward by 2 s-10^9 s (log-uniform), beyond ``max_interval_s``: exactly one
  restart, at rest at the env's lengths;
- ``clock_back``: backwards by 0.05-10 s: exactly one restart;
- ``clock_nan``: the clock set to NaN or +-inf for one step, then to 0 for the next: a
  restart each;
- ``deepcopy``, ``pickle``: the wrapper copied mid-episode; the copy and the original take
  the next :data:`COPY_STEPS` steps with the same actions and must agree bit for bit; the run
  goes on with the copy;
- ``bad_action``: a step with an action of the wrong shape, which must raise and change
  nothing (a copy taken before it and the wrapper then take the same step and must agree bit
  for bit).

Every target observes Ia, II and Ib (``afferents=("ia", "ii", "ib")``).

Checks (:class:`WrapperSoakReport`): every observation finite and in the wrapped space (the
vector's ``final_obs`` too); Ia, II and Ib in [0, ``RATE_BOUND_PPS``] pps, the tendon forces
finite, fed lengths in 0.5-1.5 L0; on the C backend, every step's Ib equal to a numpy twin
started from the C organs' state before the step and fed the forces they took, within
:data:`IB_TWIN_TOLERANCE_PPS`; the restarts counted as each clock fault says; copies equal;
refused steps leave no trace; no unexpected exception; no step longer than ``max_call_s``.
"""

from __future__ import annotations

import copy
import pickle
import time
from collections import Counter
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from spindle import core
from spindle.backends import BACKENDS

RATE_BOUND_PPS = 1000.0
"""The highest rate accepted as physiological (as the chain's soak)."""
IB_TWIN_TOLERANCE_PPS = 1e-9
"""Largest |Ib (C) - Ib (numpy twin)| accepted at a step (pps)."""
AFFERENTS = ("ia", "ii", "ib")
EPISODE_STEPS = 40
COPY_STEPS = 3
N_SUB_ENVS = 3
WRAPPER_FAULTS = ("clock_near", "clock_far", "clock_back", "clock_nan", "deepcopy", "pickle",
                  "bad_action")
TARGETS = ("single", "single_lagged", "vector")
_RESTARTING = {"clock_far": 1, "clock_back": 1, "clock_nan": 1}


def elbow_episodes() -> gym.Env:
    """The bundled elbow as a ``MuscleModelEnv`` (position servo off), episodes of
    :data:`EPISODE_STEPS` steps (module level: a vector env of these pickles)."""
    from proprio_env.body.model import model_path
    from proprio_env.wrappers.mjcf_env import MuscleModelEnv

    env = MuscleModelEnv(model_path(), frame_skip=10)
    env.model.opt.disableactuator = 1 << 2  # actuator group 2: the servo
    return gym.wrappers.TimeLimit(env, max_episode_steps=EPISODE_STEPS)


def make_target(name: str, backend: str):
    """One of :data:`TARGETS` on ``backend``, reset with seed 0."""
    from proprio_env.wrappers import SpindleAfferents, SpindleAfferentsVector

    if name == "vector":
        env = SpindleAfferentsVector(gym.vector.SyncVectorEnv(
            [elbow_episodes] * N_SUB_ENVS, autoreset_mode=AutoresetMode.SAME_STEP),
            backend=backend, afferents=AFFERENTS)
    else:
        env = SpindleAfferents(elbow_episodes(), backend=backend,
                               lag_physics_step=name == "single_lagged", afferents=AFFERENTS)
    env.reset(seed=0)
    return env


@dataclass
class WrapperSoakReport:
    """What the wrapper soak measured; :attr:`failures` lists the checks that failed."""

    steps: int = 0
    faults: Counter = field(default_factory=Counter)
    restarts: Counter = field(default_factory=Counter)
    nonfinite: Counter = field(default_factory=Counter)
    outside_space: Counter = field(default_factory=Counter)
    out_of_bounds: Counter = field(default_factory=Counter)
    restart_mismatches: list[str] = field(default_factory=list)
    copy_mismatches: list[str] = field(default_factory=list)
    half_applied: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    slow_calls: int = 0
    max_call_s: float = 0.0
    max_rate_pps: float = 0.0
    ib_twin_steps: int = 0
    ib_twin_max_diff_pps: float = 0.0
    ib_twin_mismatches: list[str] = field(default_factory=list)

    @property
    def failures(self) -> list[str]:
        out = []
        for label, value in (("non-finite observations or rates", self.nonfinite),
                             ("observations outside the wrapped space", self.outside_space),
                             ("rates or lengths out of bounds", self.out_of_bounds)):
            if sum(value.values()):
                out.append(f"{label}: {dict(value)}")
        for label, value in (("restarts not as the rule says", self.restart_mismatches),
                             ("copies that differ from their original", self.copy_mismatches),
                             ("C Ib unlike its numpy twin", self.ib_twin_mismatches),
                             ("refused steps that changed the wrapper", self.half_applied),
                             ("unexpected exceptions", self.errors)):
            if value:
                out.append(f"{label} ({len(value)}): {value[0]}")
        if self.slow_calls:
            out.append(f"{self.slow_calls} steps longer than the time limit")
        return out

    @property
    def ok(self) -> bool:
        return not self.failures

    def table(self) -> str:
        lines = [f"wrapper soak: {self.steps} steps, faults " + ", ".join(
            f"{f} {self.faults[f]}" for f in WRAPPER_FAULTS),
            "restarts counted: " + ", ".join(f"{k} {v}" for k, v in sorted(self.restarts.items())),
            f"longest step {self.max_call_s:.3f} s, highest Ia/II/Ib {self.max_rate_pps:.1f} pps",
            f"C Ib against its numpy twin: {self.ib_twin_steps} steps, largest difference "
            f"{self.ib_twin_max_diff_pps:.2e} pps"]
        return "\n".join(lines + (["FAIL: " + f for f in self.failures]
                                  or ["all wrapper checks passed"]))

    def last_line(self) -> str:
        return (f"wrapper_soak steps={self.steps} nonfinite={sum(self.nonfinite.values())} "
                f"outside_space={sum(self.outside_space.values())} "
                f"restart_mismatches={len(self.restart_mismatches)} "
                f"copy_mismatches={len(self.copy_mismatches)} "
                f"ib_twin_mismatches={len(self.ib_twin_mismatches)} "
                f"half_applied={len(self.half_applied)} errors={len(self.errors)} "
                f"ok={self.ok}")


def _bases(target) -> list:
    envs = target.env.envs if hasattr(target, "taps") else [target.env]
    return [e.unwrapped for e in envs]


def _apply_clock_fault(target, fault: str, rng: np.random.Generator) -> None:
    bases = _bases(target)
    data = bases[int(rng.integers(len(bases)))].data
    if fault == "clock_near":
        data.time += 10 ** rng.uniform(-3, np.log10(0.5))
    elif fault == "clock_far":
        data.time += 10 ** rng.uniform(np.log10(2.0), 9)
    elif fault == "clock_back":
        data.time -= rng.uniform(0.05, 10.0)
    else:
        data.time = rng.choice([np.nan, np.inf, -np.inf])


def _ib_twin_before(target):
    """(numpy twin of the C organs' state now, their step and reset counts), or None on
    numpy."""
    sense = target.forces.sense
    if sense.backend != "c":
        return None
    from spindle.tendon_organ import TendonOrgans, TendonOrganState

    organs = sense.organs
    twin = TendonOrgans(organs.force_scale_N, organs.params, organs.dt_s)
    twin.state = TendonOrganState(*organs.state_arrays())
    return twin, sense.steps, sense.resets


def _ib_twin_after(target, before, report: WrapperSoakReport, label: str) -> None:
    """Compare the C organs' rates with the twin's after one step that reset nothing."""
    sense = target.forces.sense
    if before is None or sense.steps != before[1] + 1 or sense.resets != before[2]:
        return
    f = sense.last_forces_N
    rates = before[0].run(f.transpose(1, 0, 2).reshape(f.shape[1], -1))[-1]
    diff = float(np.abs(rates - sense.ib_pps.ravel()).max())
    report.ib_twin_steps += 1
    report.ib_twin_max_diff_pps = max(report.ib_twin_max_diff_pps, diff)
    if not diff <= IB_TWIN_TOLERANCE_PPS:
        report.ib_twin_mismatches.append(f"{label}: C Ib {diff!r} pps from numpy's")


def _step(target, action, report: WrapperSoakReport, max_call_s: float, label: str):
    before = _ib_twin_before(target)
    t0 = time.perf_counter()
    out = target.step(action)
    elapsed = time.perf_counter() - t0
    _ib_twin_after(target, before, report, label)
    report.max_call_s = max(report.max_call_s, elapsed)
    report.slow_calls += elapsed > max_call_s
    report.steps += 1
    _check(target, out, report, label)
    if not hasattr(target, "taps") and (out[2] or out[3]):
        target.reset()
    return out


def _check(target, out, report: WrapperSoakReport, label: str) -> None:
    obs, info = out[0], out[4]
    finals = ([] if "final_obs" not in info else
              [o for o, m in zip(info["final_obs"], info["_final_obs"], strict=True) if m])
    space = getattr(target, "single_observation_space", None)
    arrays = [np.asarray(obs, float), *(np.asarray(f, float) for f in finals)]
    rates = np.concatenate([np.ravel(info[k]) for k in ("spindle_ia_pps", "spindle_ii_pps",
                                                         "tendon_ib_pps")])
    forces = np.ravel(info["tendon_force_N"])
    if not all(np.all(np.isfinite(a)) for a in [*arrays, rates, forces]):
        report.nonfinite[label] += 1
        return
    if not (target.observation_space.contains(obs)
            and all(space.contains(f) for f in finals)):
        report.outside_space[label] += 1
    lo, hi = core.LENGTH_RANGE_L0
    fed = info["spindle_length_L0"]
    report.max_rate_pps = max(report.max_rate_pps, float(rates.max()))
    if rates.min() < 0 or rates.max() > RATE_BOUND_PPS or fed.min() < lo or fed.max() > hi:
        report.out_of_bounds[label] += 1


def _same(a, b) -> bool:
    """Two steps' outputs equal bit for bit (NaN never appears: the checks say so)."""
    for x, y in zip(a[:4], b[:4], strict=True):
        if not np.array_equal(np.asarray(x), np.asarray(y)):
            return False
    keys = [k for k in a[4] if k.startswith(("spindle_", "tendon_")) or k == "final_obs"]
    return all(np.array_equal(np.asarray(a[4][k], dtype=object if k == "final_obs" else None),
                              np.asarray(b[4][k], dtype=object if k == "final_obs" else None))
               if k != "final_obs" else all(
                   (x is None and y is None) or np.array_equal(x, y)
                   for x, y in zip(a[4][k], b[4][k], strict=True))
               for k in keys)


def _actions(target, rng: np.random.Generator, n: int) -> list[np.ndarray]:
    shape = (N_SUB_ENVS, 3) if hasattr(target, "taps") else (3,)
    out = rng.uniform(0.0, 1.0, (n, *shape)).astype(np.float32)
    out[..., 2] = 0.0
    return list(out)


def _copy_fault(target, fault: str, rng, report, max_call_s, label):
    """Copy mid-episode; both take the same steps; the run goes on with the copy."""
    clone = copy.deepcopy(target) if fault == "deepcopy" else pickle.loads(pickle.dumps(target))
    for k, action in enumerate(_actions(target, rng, COPY_STEPS)):
        a = _step(target, action, report, max_call_s, label)
        b = _step(clone, action, report, max_call_s, label)
        if not _same(a, b):
            report.copy_mismatches.append(f"{label}: {fault}, step {k} after the copy")
            break
    target.close()
    return clone


def _bad_action_fault(target, rng, report, max_call_s, label) -> None:
    """A wrong-shape action must raise and leave the wrapper as a copy taken before it."""
    before = copy.deepcopy(target)
    wrong = np.zeros((N_SUB_ENVS, 5) if hasattr(target, "taps") else 5, np.float32)
    try:
        target.step(wrong)
    except (ValueError, IndexError, AssertionError):
        pass
    else:
        report.half_applied.append(f"{label}: a wrong-shape action was accepted")
    action = _actions(target, rng, 1)[0]
    if not _same(_step(target, action, report, max_call_s, label),
                 _step(before, action, report, max_call_s, label)):
        report.half_applied.append(f"{label}: the wrapper changed after a refused step")
    before.close()


def _clock_fault(target, fault, rng, report, max_call_s, label) -> None:
    _apply_clock_fault(target, fault, rng)
    restarts = target.bank.restarts
    out = _step(target, _actions(target, rng, 1)[0], report, max_call_s, label)
    delta = target.bank.restarts - restarts
    report.restarts[fault] += delta
    want = _RESTARTING.get(fault)
    if want is not None and delta != want:
        report.restart_mismatches.append(f"{label}: {fault} gave {delta} restarts, not {want}")
    if fault == "clock_nan":  # each clock set back to 0 (unless a reset did): one restart
        repaired = 0
        for base in _bases(target):
            if not np.isfinite(base.data.time):
                base.data.time, repaired = 0.0, repaired + 1
        restarts = target.bank.restarts
        _step(target, _actions(target, rng, 1)[0], report, max_call_s, label)
        if target.bank.restarts - restarts != repaired:
            report.restart_mismatches.append(
                f"{label}: {repaired} clocks from NaN/inf back to 0 gave "
                f"{target.bank.restarts - restarts} restarts")
    if fault == "clock_far" and not hasattr(target, "taps"):
        rest = core.equilibrium_state(out[4]["spindle_length_L0"], 100.0, 85.0, target.bank.params)
        ia, _ = core.afferents(rest, target.bank.params)
        if not np.allclose(out[4]["spindle_ia_pps"], ia, rtol=0, atol=1e-9):
            report.restart_mismatches.append(f"{label}: not at rest after {fault}")


def run_wrapper_soak(n_steps: int, seed: int = 0, fault_probability: float = 0.2,
                     max_call_s: float = 5.0, targets: tuple[str, ...] = TARGETS,
                     backends: tuple[str, ...] = BACKENDS) -> WrapperSoakReport:
    """About ``n_steps`` wrapped steps per target and backend with faults between them."""
    report = WrapperSoakReport()
    for b_index, backend in enumerate(backends):
        for t_index, name in enumerate(targets):
            rng = np.random.default_rng([seed, b_index, t_index])
            label = f"{name}/{backend}"
            target = make_target(name, backend)
            done = report.steps
            while report.steps - done < n_steps:
                fault = (WRAPPER_FAULTS[int(rng.integers(len(WRAPPER_FAULTS)))]
                         if rng.random() < fault_probability else "")
                try:
                    if fault:
                        report.faults[fault] += 1
                    if fault in ("deepcopy", "pickle"):
                        target = _copy_fault(target, fault, rng, report, max_call_s, label)
                    elif fault == "bad_action":
                        _bad_action_fault(target, rng, report, max_call_s, label)
                    elif fault:
                        _clock_fault(target, fault, rng, report, max_call_s, label)
                    else:
                        _step(target, _actions(target, rng, 1)[0], report, max_call_s, label)
                except Exception as exc:  # a wrapper step must not raise: record, go on
                    report.errors.append(f"{label}: {fault or 'clean'}: "
                                         f"{type(exc).__name__}: {str(exc)[:160]}")
                    target.close()
                    target = make_target(name, backend)
            target.close()
    return report
