"""The fault soak's vector-env section: refused resets between steps change nothing.

A native vector env (:mod:`proprio_env.envs.vector`, both ids, ``n`` sub-envs) and its twin,
built alike and fed the same actions, step side by side. Before a share of the steps the soak
tries a reset that must be refused (:data:`BAD_RESETS`: a bool, string, complex or NaN target,
an out-of-range angle for one sub-env, a wrong-length option, a fractional or string seed, a
bad seed inside a list, an unknown option, a bad reset mask) on the soaked env only; before
others it resets both with the same good seeds and options (a masked reset of some sub-envs
included). After every step the two must be equal bit for bit (observations, rewards, the
raw signals of ``info``), every observation finite and inside the observation space: a
refused reset that changed anything (a half-applied reset) shows as a difference at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

BAD_RESETS = ("target_bool", "target_str", "target_complex", "target_nan", "angle_out_of_range",
              "wrong_length", "seed_fraction", "seed_str", "seed_list_bad", "unknown_option",
              "bad_mask")
"""The refused resets the soak injects."""
ENV_IDS = ("proprio_env/ElbowReach-v1", "proprio_env/ProsthesisElbow-v1")


@dataclass
class VectorSoakReport:
    """What the vector-env section saw, per env id: steps, refused resets by kind, good
    resets, steps on which the soaked env differed from its twin (must be 0), non-finite or
    out-of-space observations (0), refusals that were not ``ValueError``/``TypeError`` (0)."""

    steps: int = 0
    refused: dict[str, int] = field(default_factory=lambda: dict.fromkeys(BAD_RESETS, 0))
    good_resets: int = 0
    differing_steps: int = 0
    bad_observations: int = 0
    wrong_errors: int = 0

    @property
    def ok(self) -> bool:
        return (self.differing_steps == 0 and self.bad_observations == 0
                and self.wrong_errors == 0)

    def last_line(self) -> str:
        return (f"vector_soak steps={self.steps} refused={sum(self.refused.values())} "
                f"good_resets={self.good_resets} differing_steps={self.differing_steps} "
                f"bad_observations={self.bad_observations} ok={self.ok}")


def bad_reset(kind: str, n: int, rng: np.random.Generator) -> dict[str, Any]:
    """The ``reset`` keyword arguments of a refused reset of kind ``kind`` for ``n`` sub-envs."""
    i = int(rng.integers(n))
    targets = list(rng.uniform(20.0, 110.0, n))
    if kind in ("target_bool", "target_str", "target_complex", "target_nan"):
        targets[i] = {"target_bool": True, "target_str": "70", "target_complex": 70 + 0j,
                      "target_nan": float("nan")}[kind]
        return {"options": {"target_deg": targets}}
    if kind == "angle_out_of_range":
        angles = list(rng.uniform(20.0, 110.0, n))
        angles[i] = 400.0
        return {"options": {"angle_deg": angles}}
    if kind == "wrong_length":
        return {"options": {"target_deg": targets[:-1] if n > 1 else targets * 2}}
    if kind == "seed_fraction":
        return {"seed": 1.5}
    if kind == "seed_str":
        return {"seed": "3"}
    if kind == "seed_list_bad":
        seeds: list[Any] = [int(s) for s in rng.integers(0, 1000, n)]
        seeds[i] = -1
        return {"seed": seeds}
    if kind == "unknown_option":
        return {"options": {"target": 60.0}}
    if kind == "bad_mask":
        return {"options": {"reset_mask": np.ones(n + 1, dtype=bool)}}
    raise ValueError(f"unknown bad reset {kind!r}")


def good_reset(n: int, rng: np.random.Generator) -> dict[str, Any]:
    """A good reset: new seeds and targets for every sub-env, or a masked reset of some."""
    seeds = [int(s) for s in rng.integers(0, 10**6, n)]
    if rng.random() < 0.5:
        return {"seed": seeds, "options": {"target_deg": rng.uniform(20.0, 110.0, n)}}
    mask = rng.random(n) < 0.5
    mask[int(rng.integers(n))] = True
    return {"options": {"reset_mask": mask, "target_deg": rng.uniform(20.0, 110.0, n)}}


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


def soak_vector_resets(env_id: str, n_steps: int, num_envs: int = 3, seed: int = 0,
                       fault_probability: float = 0.2) -> VectorSoakReport:
    """The section on one env id (see the module docstring); returns its report."""
    rng = np.random.default_rng(seed)
    envs = [gym.make_vec(env_id, num_envs=num_envs) for _ in range(2)]
    soaked = envs[0]  # envs[1] is its twin: it never sees a refused reset
    report = VectorSoakReport()
    try:
        for env in envs:
            env.reset(seed=seed)
        space = soaked.observation_space
        for _ in range(n_steps):
            draw = rng.random()
            if draw < fault_probability:
                kind = BAD_RESETS[int(rng.integers(len(BAD_RESETS)))]
                try:
                    soaked.reset(**bad_reset(kind, num_envs, rng))
                except (ValueError, TypeError):
                    report.refused[kind] += 1
                except Exception:  # any other error is a finding, counted
                    report.wrong_errors += 1
                else:
                    report.wrong_errors += 1  # accepted: the envs now differ, counted below
            elif draw < fault_probability * 1.25:
                kwargs = good_reset(num_envs, rng)
                for env in envs:
                    env.reset(**kwargs)
                report.good_resets += 1
            actions = soaked.action_space.sample()
            out = [env.step(actions) for env in envs]
            report.steps += 1
            if not all(_same(x, y) for x, y in zip(out[0], out[1], strict=True)):
                report.differing_steps += 1
            obs = out[0][0]
            if not (np.all(np.isfinite(obs)) and space.contains(obs)):
                report.bad_observations += 1
    finally:
        for env in envs:
            env.close()
    return report


def run_vector_soak(n_steps: int, seed: int = 0) -> dict[str, VectorSoakReport]:
    """The section on both ids: {env id: report}."""
    return {env_id: soak_vector_resets(env_id, n_steps, seed=seed) for env_id in ENV_IDS}
