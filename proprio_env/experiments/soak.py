"""Soak of the envs: many random-action steps; no NaN/inf in any observation and the state
stays bounded. Every 1000 steps a NaN action and an out-of-box action are tried: each must
raise ``ValueError`` and leave the state untouched. Command line: ``python scripts/soak_env.py``.

Bounds checked at every step: elbow angle within the joint range +- 5 deg (soft joint
limits), |angular velocity| < 5000 deg/s, Ia and II in [0, 1000) pps, gamma drives finite and
>= 0, the spindles' lengths inside their valid range; with Ib (the ``-v1`` ids) Ib in
[0, 1000) pps and the tendon forces finite and >= 0, and, when the env's tendon organs run in
C, Ib equal to a numpy twin fed the same forces within :data:`IB_TWIN_TOLERANCE_PPS` at every
step. :func:`soak` prints progress (steps/s, ETA), returns the extremes seen and raises
:class:`SoakError` on the first violation.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

ANGLE_MARGIN_DEG = 5.0
MAX_SPEED_DEG_S = 5000.0
MAX_RATE_PPS = 1000.0
IB_TWIN_TOLERANCE_PPS = 1e-9
"""Largest |Ib (C) - Ib (numpy twin)| accepted at any step (pps)."""


class SoakError(AssertionError):
    """A bound was violated."""


def check_step(obs: np.ndarray, info: dict[str, Any], joint_range_deg, step: int) -> None:
    lo, hi = joint_range_deg
    problems = []
    if not np.all(np.isfinite(obs)):
        problems.append(f"non-finite observation {obs.tolist()}")
    if not (lo - ANGLE_MARGIN_DEG <= info["angle_deg"] <= hi + ANGLE_MARGIN_DEG):
        problems.append(f"angle {info['angle_deg']!r} deg outside the joint range")
    if not abs(info["angular_velocity_deg_s"]) < MAX_SPEED_DEG_S:
        problems.append(f"angular velocity {info['angular_velocity_deg_s']!r} deg/s")
    for key in ("ia_pps", "ii_pps", "ib_pps"):
        if key not in info:
            continue
        r = info[key]
        if not (np.all(np.isfinite(r)) and np.all(r >= 0) and np.all(r < MAX_RATE_PPS)):
            problems.append(f"{key} {r.tolist()} outside [0, {MAX_RATE_PPS})")
    for key in ("gamma_static_pps", "gamma_dynamic_pps"):
        g = info[key]
        if not (np.all(np.isfinite(g)) and np.all(g >= 0)):
            problems.append(f"{key} {g.tolist()}")
    if "force_N" in info and not (np.all(np.isfinite(info["force_N"]))
                                  and np.all(info["force_N"] >= 0)):
        problems.append(f"force_N {info['force_N'].tolist()} not finite and >= 0")
    if not (np.all(info["length_L0"] > 0.5) and np.all(info["length_L0"] < 1.5)):
        problems.append(f"length_L0 {info['length_L0'].tolist()} outside (0.5, 1.5)")
    if problems:
        raise SoakError(f"step {step}: " + "; ".join(problems))


class IbTwin:
    """A numpy twin of a C env's tendon organs (``env.unwrapped.tendon_organs``), fed the
    forces the env's organs took at every step: :meth:`check` returns |C - numpy| (pps)."""

    def __init__(self, sense: Any) -> None:
        from spindle.tendon_organ import TendonOrgans

        self.sense = sense
        self.organs = TendonOrgans(sense.organs.force_scale_N, sense.organs.params,
                                   sense.organs.dt_s)
        self.reset()

    def reset(self) -> None:
        """At rest at the env's current forces (after an env reset)."""
        self.organs.reset(self.sense.force_N.ravel())

    def check(self) -> float:
        f = self.sense.last_forces_N
        rates = self.organs.run(f.transpose(1, 0, 2).reshape(f.shape[1], -1))[-1]
        return float(np.abs(rates - self.sense.ib_pps.ravel()).max())


def soak(env_id: str, steps: int, seed: int = 0, report_every: int = 0,
         max_minutes: float = math.inf, **env_kwargs: Any) -> dict[str, Any]:
    """Run ``steps`` random-action steps of ``env_id`` (fewer if ``max_minutes`` of wall time
    run out first); raise :class:`SoakError` on a bound violation. Returns the number of
    steps done, the extremes seen and the rate."""
    import gymnasium as gym

    import proprio_env  # noqa: F401  (registers the envs)

    env = gym.make(env_id, **env_kwargs)
    base = env.unwrapped
    space = env.action_space
    space.seed(seed)
    n_act = space.shape[0]
    env.reset(seed=seed)
    extremes = {"angle_deg": [math.inf, -math.inf], "ia_pps": [math.inf, -math.inf],
                "ii_pps": [math.inf, -math.inf]}
    sense = getattr(base, "tendon_organs", None)
    twin = IbTwin(sense) if sense is not None and sense.backend == "c" else None
    if sense is not None:
        extremes["ib_pps"] = [math.inf, -math.inf]
        extremes["force_N"] = [math.inf, -math.inf]
    twin_diff = 0.0
    episodes, rejected = 1, 0
    start = time.perf_counter()
    done = 0
    for step in range(1, steps + 1):
        if step % 1000 == 0 and time.perf_counter() - start > 60 * max_minutes:
            break
        if step % 1000 == 0:
            before = (base.data.time, base.angle_deg)
            for bad in (np.full(n_act, np.nan), space.high + 1.0):
                try:
                    env.step(bad)
                except ValueError:
                    rejected += 1
                else:
                    raise SoakError(f"step {step}: bad action {bad.tolist()} was accepted")
            if (base.data.time, base.angle_deg) != before:
                raise SoakError(f"step {step}: a rejected action changed the state")
        obs, _, terminated, truncated, info = env.step(space.sample())
        check_step(obs, info, base.joint_range_deg, step)
        if twin is not None:
            diff = twin.check()
            twin_diff = max(twin_diff, diff)
            if not diff <= IB_TWIN_TOLERANCE_PPS:
                raise SoakError(f"step {step}: Ib of the C organs is {diff!r} pps from the "
                                f"numpy twin's (limit {IB_TWIN_TOLERANCE_PPS})")
        for key in extremes:
            v = np.asarray(info[key])
            extremes[key][0] = min(extremes[key][0], float(v.min()))
            extremes[key][1] = max(extremes[key][1], float(v.max()))
        done = step
        if terminated or truncated:
            env.reset()
            episodes += 1
            if twin is not None:
                twin.reset()
        if report_every and step % report_every == 0:
            _progress(step, steps, start, extremes, "steps")
    elapsed = time.perf_counter() - start
    counters = dict(base.afferents.chain.counters)
    env.close()
    out = {"steps": done, "episodes": episodes, "elapsed_s": elapsed,
           "steps_per_s": done / elapsed, "bad_actions_rejected": rejected,
           "extremes": extremes, "chain_counters_last_episode": counters}
    if twin is not None:
        out["ib_numpy_c_max_diff_pps"] = twin_diff
    if sense is not None:
        out["force_rule"] = {"held": int(sense.held.sum()), "clamped": int(sense.clamped.sum())}
    return out


def soak_vector(env_id: str, env_steps: int, num_envs: int = 64, seed: int = 0,
                report_every: int = 0, max_minutes: float = math.inf,
                **env_kwargs: Any) -> dict[str, Any]:
    """The soak of the native vector env (``gymnasium.make_vec``): ``env_steps`` env steps
    (``num_envs`` per vector step) of random actions, a third of them at the box's corners,
    with autoresets; every observation must be finite and inside the observation space, and
    every sub-env's signals inside the bounds of :func:`check_step`. Returns as :func:`soak`
    (``steps`` counts env steps)."""
    import gymnasium as gym

    import proprio_env  # noqa: F401  (registers the envs)

    env = gym.make_vec(env_id, num_envs=num_envs, **env_kwargs)
    base = env.unwrapped
    space = env.single_action_space
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    joint_range = base.joint_range_deg
    extremes = {"angle_deg": [math.inf, -math.inf], "ia_pps": [math.inf, -math.inf],
                "ii_pps": [math.inf, -math.inf]}
    if getattr(base, "tendon_organs", None) is not None:
        extremes["ib_pps"] = [math.inf, -math.inf]
    episodes, done, vstep = num_envs, 0, 0
    start = time.perf_counter()
    while done < env_steps:
        if vstep % 100 == 0 and time.perf_counter() - start > 60 * max_minutes:
            break
        vstep += 1
        actions = rng.uniform(space.low, space.high, (num_envs, *space.shape))
        if vstep % 3 == 0:
            corners = rng.random(actions.shape) < 0.5
            actions = np.where(corners, space.low, space.high)
        obs, _, terminated, truncated, info = env.step(actions.astype(np.float32))
        if not (np.all(np.isfinite(obs)) and env.observation_space.contains(obs)):
            bad = int(np.argmin(np.isfinite(obs).all(axis=1)))
            raise SoakError(f"vector step {vstep}: observation {obs[bad].tolist()} of env "
                            f"{bad} is not finite or outside the observation space")
        for key in extremes:
            v = np.asarray(info[key])
            extremes[key][0] = min(extremes[key][0], float(v.min()))
            extremes[key][1] = max(extremes[key][1], float(v.max()))
        if (vstep % 50 == 0 or done + num_envs >= env_steps):
            for i in range(num_envs):
                check_step(obs[i], {k: v[i] for k, v in info.items()}, joint_range, done + i)
        episodes += int(np.sum(terminated | truncated))
        done += num_envs
        if report_every and done // report_every != (done - num_envs) // report_every:
            _progress(done, env_steps, start, extremes, "env steps")
    elapsed = time.perf_counter() - start
    env.close()
    return {"steps": done, "episodes": episodes, "elapsed_s": elapsed,
            "steps_per_s": done / elapsed, "bad_actions_rejected": 0, "extremes": extremes}


def _progress(done: int, total: int, start: float, extremes: dict, unit: str) -> None:
    """One progress line: steps so far, rate, time left, the angle range seen."""
    rate = done / (time.perf_counter() - start)
    print(f"{done:10d}/{total} {unit} | {rate:8.1f} {unit}/s | ETA "
          f"{(total - done) / rate / 60:7.1f} min | angle "
          f"{extremes['angle_deg'][0]:.1f}..{extremes['angle_deg'][1]:.1f} deg", flush=True)
