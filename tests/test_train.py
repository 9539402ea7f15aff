"""Smoke run of scripts/train.py (:mod:`proprio_env.training.sb3`): PPO trains, the
three policies are evaluated on held-out targets, and the learning curve and numbers are
written."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("matplotlib")

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "train.py"

from proprio_env.training import rllib as trl  # noqa: E402
from proprio_env.training import sb3 as train  # noqa: E402


def test_held_out_bands_are_never_trained_on():
    ranges = train.training_ranges()
    for lo, hi in ranges:
        for a, b in train.HELD_OUT_BANDS:
            assert hi <= a or lo >= b
    covered = sum(hi - lo for lo, hi in ranges) + sum(b - a for a, b in train.HELD_OUT_BANDS)
    assert covered == pytest.approx(train.TARGET_SPAN_DEG[1] - train.TARGET_SPAN_DEG[0])
    targets = train.held_out_targets(9)
    assert all(any(a < t < b for a, b in train.HELD_OUT_BANDS) for t in targets)


def test_smoke_run_trains_evaluates_and_plots(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    # --smoke alone is the short run (256 env steps), as CI calls it
    run = subprocess.run([sys.executable, str(SCRIPT), "--smoke", "--out", str(tmp_path)],
                         capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["train"]["timesteps"] == 256
    for name in ("ppo", "zero", "random"):
        score = result[name]["mean_abs_err_deg"]
        assert np.isfinite(score)
        # the printed score is the written one
        assert f"{name} mean_abs_err_deg={score:.2f} " in run.stdout
    # Zero excitation: the arm hangs near straight under gravity (passive muscles only), so
    # the error is the held-out targets' mean (37.5, 62.5, 87.5 deg -> 62.5) minus a small
    # hanging angle.
    assert 62.5 - 15 < result["zero"]["mean_abs_err_deg"] < 62.5
    assert (tmp_path / "policy.zip").stat().st_size > 1000
    assert (tmp_path / "curve.png").stat().st_size > 5000
    with (tmp_path / "curve.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["timesteps"]) for r in rows] == [128, 256]  # one row per 128-step rollout
    progress = [line.split()[1] for line in run.stdout.splitlines() if line.startswith("steps")]
    assert progress == ["128/256", "256/256"]
    assert all(float(r["elapsed_s"]) > 0 and np.isfinite(float(r["train_abs_err_deg"]))
               for r in rows)


def test_the_total_is_the_whole_rollouts_a_run_takes():
    # SB3 and RLlib stop after the rollout that reaches the requested steps: 250,000 at
    # 2048 per rollout runs 123 rollouts (122 make 249,856)
    assert train.whole_rollouts(250_000, 2048) == 123 * 2048 == 251_904
    assert train.whole_rollouts(2048, 2048) == 2048
    assert train.whole_rollouts(1, 128) == 128
    line = train.progress_line(251_904, train.whole_rollouts(250_000, 2048), 60.0, 3.0,
                               float("nan"))
    assert line.startswith("steps  251904/251904 |")


def test_options_refuse_bad_values():
    with pytest.raises(ValueError, match="num_envs=0"):
        train.TrainConfig(num_envs=0)
    with pytest.raises(ValueError, match="num_envs=True"):
        train.TrainConfig(num_envs=True)
    with pytest.raises(ValueError, match="num_env_runners=-1"):
        trl.RLlibOptions(num_env_runners=-1)
    with pytest.raises(ValueError, match="num_cpus=0"):
        trl.RLlibOptions(num_cpus=0)
    with pytest.raises(ValueError, match="checkpoint_dir"):
        trl.RLlibOptions(resume=True)


def test_env_id_imports_the_package_that_registers_it():
    assert trl.rllib_env_id("proprio_env/ElbowReach-v0") == "proprio_env:proprio_env/ElbowReach-v0"
    # a fresh interpreter that never imported proprio_env builds the env from the prefixed id
    code = ("import gymnasium as gym; env = gym.make('proprio_env:proprio_env/ElbowReach-v0'); "
            "print(env.reset(seed=0)[0].shape)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "(5,)"


def test_runner_seeds_are_disjoint():
    seeds = {trl.runner_seed(7, k, 8) + i for k in range(1, 5) for i in range(8)}
    assert seeds == set(range(7 + 8, 7 + 5 * 8))


def test_module_policy_maps_normalised_actions_onto_the_box():
    torch = pytest.importorskip("torch")

    class Dist:
        def __init__(self, mean):
            self.mean = mean

        @classmethod
        def from_logits(cls, logits):
            return cls(logits[:, :2])

        def to_deterministic(self):
            return self

        def sample(self):
            return self.mean

    class Module:
        def get_inference_action_dist_cls(self):
            return Dist

        def forward_inference(self, batch):
            obs = batch["obs"]
            return {"action_dist_inputs": torch.cat([obs[:, :2], obs[:, :2]], dim=1)}

    space = gym.spaces.Box(0.0, 1.0, (2,), dtype=np.float32)
    policy = trl.module_policy(Module(), space)
    # [-1, 1] -> [0, 1]; beyond the range clipped
    np.testing.assert_allclose(policy(np.array([-1.0, 0.0, 9.0], np.float32), None), [0.0, 0.5])
    np.testing.assert_allclose(policy(np.array([1.0, 3.0, 9.0], np.float32), None), [1.0, 1.0])


@pytest.mark.parametrize(("args", "message"), [
    (["--num-envs", "3"], "num_envs=3 must divide the rollout of 2048"),
    (["--address", "auto"], "--address belong to --engine rllib"),
    (["--engine", "rllib", "--num-envs", "4"], "--num-envs belongs to --engine sb3"),
    (["--engine", "rllib", "--resume"], "resume=True needs a checkpoint_dir"),
])
def test_bad_arguments_are_refused_before_anything_starts(args, message, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    run = subprocess.run([sys.executable, str(SCRIPT), *args, "--out", str(tmp_path)],
                         capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 2
    assert message in run.stderr
    assert not (tmp_path / "eval.json").exists()


def _train_script(monkeypatch):
    """scripts/train.py as a module whose engines and env builders fail if reached."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    class Reached(Exception):
        pass

    def reached(*args, **kwargs):
        raise Reached

    for name in ("run_sb3", "run_rllib"):
        monkeypatch.setattr(module, name, reached)
    for name in ("make", "make_vec"):
        monkeypatch.setattr(gym, name, reached)
    return module, Reached


def _checkpoint(path: Path, env_id: str) -> Path:
    path.mkdir()
    trl.write_curve(path, [[128, 1.0, 30.0, 40.0]], 1.0, env_id)
    return path


@pytest.mark.parametrize(("args", "message"), [
    (["--afferent-source", "bogus"], "afferent_source='bogus' is not one of"),
    (["--seed", "-1"], "seed=-1 must be an integer in 0..2147483647"),
    (["--seed", str(2**31)], f"seed={2**31} must be an integer in 0.."),
    (["--curve-episodes", "-1"], "curve_episodes=-1 must be an integer >= 1"),
    (["--curve-episodes", "0"], "curve_episodes=0 must be an integer >= 1"),
    (["--eval-every", "0"], "eval_every=0 must be an integer >= 1"),
    (["--eval-episodes", "0"], "eval_episodes=0 must be an integer >= 1"),
    (["--timesteps", "-5"], "timesteps=-5 must be an integer >= 1"),
    (["--max-minutes", "nan"], "max_minutes=nan must be a finite real number > 0"),
    (["--max-minutes", "0"], "max_minutes=0.0 must be a finite real number > 0"),
    (["--env", "proprio_env/Nope-v0"], "env_id='proprio_env/Nope-v0' is not a registered"),
    (["--env", "no_such_module:Env-v0"], "its module 'no_such_module' does not import"),
    (["--out", "{file}"], "is a file; it must be a folder"),
    (["--curve", "{dir}"], "is a folder; it must be a PNG's path"),
    (["--engine", "rllib", "--checkpoint-dir", "{file}"], "is a file, not a folder"),
    (["--engine", "rllib", "--resume", "--checkpoint-dir", "{dir}/missing"],
     "does not exist: nothing to resume"),
    (["--engine", "rllib", "--resume", "--checkpoint-dir", "{dir}"],
     "holds no checkpoint of a training run"),
    (["--engine", "rllib", "--resume", "--checkpoint-dir", "{prosthesis}"],
     "was trained on env 'proprio_env/ProsthesisElbow-v0', not 'proprio_env/ElbowReach-v0'"),
])
def test_every_argument_is_checked_before_an_env_or_ray_exists(args, message, tmp_path,
                                                              monkeypatch, capsys):
    """These used to fail after the env was built (a bad source, a negative seed), be
    accepted (NaN curve points from --curve-episodes -1, --eval-every 0), or raise
    FileNotFoundError / a torch size mismatch after Ray had started (--resume)."""
    script, _ = _train_script(monkeypatch)
    places = {"file": tmp_path / "a-file", "dir": tmp_path,
              "prosthesis": tmp_path / "ckpt-prosthesis"}
    places["file"].write_text("x")
    _checkpoint(places["prosthesis"], "proprio_env/ProsthesisElbow-v0")
    argv = [a.format(**places) for a in args]
    # Ray unloaded for the call (another test of this process may have imported it), so that
    # only this command's own import of it would show
    for name in [m for m in sys.modules if m == "ray" or m.startswith("ray.")]:
        monkeypatch.delitem(sys.modules, name)
    with pytest.raises(SystemExit) as exit_info:
        script.main(argv + (["--out", str(tmp_path / "out")] if "--out" not in argv else []))
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert "ray" not in sys.modules
    assert not (tmp_path / "out").exists()


def test_good_arguments_and_a_matching_checkpoint_reach_the_engine(tmp_path, monkeypatch):
    script, reached = _train_script(monkeypatch)
    ckpt = _checkpoint(tmp_path / "ckpt", "proprio_env/ElbowReach-v0")
    for argv in (["--seed", "0", "--curve-episodes", "1", "--eval-every", "1"],
                 ["--engine", "rllib", "--resume", "--checkpoint-dir", str(ckpt),
                  "--seed", str(train.MAX_SEED)]):
        with pytest.raises(reached):
            script.main([*argv, "--out", str(tmp_path / "out")])
