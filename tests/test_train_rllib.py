"""The RLlib engine of scripts/train.py (:mod:`proprio_env.training.rllib`) on a
local Ray instance of 2 CPUs: the smoke run, the env runners' envs and seeds, a runner killed
mid-training, a run stopped and resumed from its checkpoint.

Needs the ``distributed`` extra; all slow (Ray takes ~20 s to start). Its parts that need no
Ray are tested in ``tests/test_train.py``."""

from __future__ import annotations

import csv
import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

ray = pytest.importorskip("ray")
pytest.importorskip("ray.rllib")
pytest.importorskip("matplotlib")

from proprio_env.training import rllib as trl  # noqa: E402
from proprio_env.training import sb3 as train  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "train.py"




def run_script(*args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, str(SCRIPT), "--engine", "rllib", *args],
                          capture_output=True, text=True, env=env, timeout=timeout)


@pytest.mark.slow
def test_rllib_smoke_run_trains_evaluates_and_saves_the_policy(tmp_path):
    run = run_script("--smoke", "--timesteps", "256", "--out", str(tmp_path))
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["train"]["engine"] == "rllib"
    assert result["train"]["timesteps"] == 256
    for name in ("ppo", "zero", "random"):
        score = result[name]["mean_abs_err_deg"]
        assert np.isfinite(score)
        assert f"{name} mean_abs_err_deg={score:.2f} " in run.stdout
    # the engine-independent policies score exactly as in the SB3 path (same protocol)
    zero = train.evaluate(train.zero_policy, "proprio_env/ElbowReach-v0", {"backend": "c"}, 3,
                          seed=train.EVAL_SEED)
    assert result["zero"]["mean_abs_err_deg"] == pytest.approx(zero["mean_abs_err_deg"],
                                                               abs=1e-9)
    with (tmp_path / "curve.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["timesteps"]) for r in rows] == [128, 256]  # one row per 128-step batch
    assert all(np.isfinite(float(r["train_abs_err_deg"])) for r in rows)
    assert (tmp_path / "curve.png").stat().st_size > 5000
    # the saved policy, loaded back, is the policy that was scored
    from ray.rllib.core.rl_module.rl_module import RLModule

    module = RLModule.from_checkpoint(str(tmp_path / "policy"))
    space = gym.spaces.Box(0.0, 1.0, (2,), dtype=np.float32)
    again = train.evaluate(trl.module_policy(module, space), "proprio_env/ElbowReach-v0",
                           {"backend": "c"}, 3, seed=train.EVAL_SEED)
    assert again["mean_abs_err_deg"] == pytest.approx(result["ppo"]["mean_abs_err_deg"],
                                                      abs=1e-6)


@pytest.mark.slow
def test_a_run_stopped_and_resumed_from_its_checkpoint(tmp_path):
    ckpt = tmp_path / "ckpt"
    first = run_script("--smoke", "--timesteps", "256", "--checkpoint-dir", str(ckpt),
                       "--out", str(tmp_path / "a"))
    assert first.returncode == 0, first.stderr[-3000:]
    resumed = run_script("--smoke", "--timesteps", "512", "--checkpoint-dir", str(ckpt),
                         "--resume", "--out", str(tmp_path / "b"))
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "resumed at 256 steps" in resumed.stdout
    result = json.loads((tmp_path / "b" / "eval.json").read_text())
    assert result["train"]["timesteps"] == 512 and result["train"]["resumed"]
    with (tmp_path / "b" / "curve.csv").open(newline="") as fh:
        rows = [int(r["timesteps"]) for r in csv.DictReader(fh)]
    # the curve goes on from the checkpoint: the first run's rows, then the resumed ones
    assert rows == [128, 256, 384, 512]


# The tests below share one local Ray instance in this process; the script runs above start
# their own in subprocesses, so they come first (a script run starting its local instance
# while this process held another failed once here: "Failed to register worker to Raylet").
@pytest.fixture(scope="module")
def local_ray():
    trl.start_ray(trl.RLlibOptions())
    yield
    ray.shutdown()


def runner_pids(algo) -> list[int]:
    return sorted(algo.env_runner_group.foreach_env_runner(lambda r: os.getpid(),
                                                           local_env_runner=False))


@pytest.mark.slow
def test_runners_step_the_vector_env_with_disjoint_seeds(local_ray):
    n = 3
    config = train.TrainConfig(seed=5, num_envs=n)
    algo = trl.build_algorithm(config, trl.RLlibOptions(num_env_runners=2), quick=True)
    try:
        got = algo.env_runner_group.foreach_env_runner(
            lambda r: (r.worker_index, r.env.num_envs, r.env.unwrapped.spec.id,
                       r.env.reset(seed=r._seed)[0]), local_env_runner=False)
    finally:
        algo.stop()
    assert sorted(k for k, *_ in got) == [1, 2]
    for k, num_envs, spec_id, obs in got:
        assert num_envs == n and spec_id == "proprio_env/ElbowReach-v0"
        # sub-env i of runner k starts as a single env reset with seed 5 + k * n + i
        for i in range(n):
            single = gym.make("proprio_env/ElbowReach-v0", backend="c",
                              target_ranges_deg=train.training_ranges())
            expected, _ = single.reset(seed=5 + k * n + i)
            np.testing.assert_allclose(obs[i], expected, atol=1e-6)


@pytest.mark.slow
def test_a_killed_env_runner_is_restarted_and_training_goes_on(local_ray):
    config = train.TrainConfig(seed=0, num_envs=4)
    algo = trl.build_algorithm(config, trl.RLlibOptions(num_env_runners=2), quick=True)
    try:
        algo.train()
        before = runner_pids(algo)
        assert len(before) == 2
        victim = before[0]
        # kill the runner's process while an iteration is sampling
        killer = threading.Timer(0.3, os.kill, (victim, signal.SIGKILL))
        killer.start()
        steps = []
        for _ in range(6):
            steps.append(trl.env_steps(algo.train()))
        killer.join()
        deadline = time.monotonic() + 120
        after: list[int] = []
        while time.monotonic() < deadline:
            result = algo.train()
            steps.append(trl.env_steps(result))
            if algo.env_runner_group.num_healthy_remote_workers() == 2:
                after = runner_pids(algo)
                break
        assert victim not in after and len(after) == 2, (before, after)
        assert algo.env_runner_group.num_remote_worker_restarts() >= 1
        # training went on through the failure: the sample counter kept rising
        assert all(b > a for a, b in itertools.pairwise(steps))
        # the restarted runner samples again: both runners' steps fill the next batches
        by_runner = trl.steps_by_runner(algo.train())
        by_runner2 = trl.steps_by_runner(algo.train())
        assert sorted(by_runner) == sorted(by_runner2) == [1, 2], (by_runner, by_runner2)
        assert min(by_runner.values()) > 0 and min(by_runner2.values()) > 0
    finally:
        algo.stop()
