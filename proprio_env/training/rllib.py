"""The training protocol of :mod:`proprio_env.training.sb3` on Ray RLlib: PPO whose env
runners each step a batched env, on a local Ray instance or a running cluster, with
checkpoints and env-runner restart.

- Envs: RLlib's runners build ``gym.make_vec("proprio_env:<id>", num_envs,
  vectorization_mode=...)`` themselves. The ``proprio_env:`` prefix makes Gymnasium import
  ``proprio_env`` (which registers the ids) in every worker process, so no registration code
  runs on the cluster. The vectorisation is Gymnasium's default for the id: the env's own
  vector env (``vector_entry_point``) when it declares one, ``SyncVectorEnv`` otherwise.
- Seeds: runner k (1, 2, ...; 0 is the driver's local runner) resets its sub-env i with
  ``seed + k * num_envs + i`` (:class:`ProprioEnvRunner`), so no two sub-envs anywhere share a
  seed and a restarted runner starts over from its own seeds. RLlib's default,
  ``seed + k`` per runner, would give runner 1's sub-env 1 and runner 2's sub-env 0 the same
  episodes.
- PPO: the SB3 run's settings where RLlib has them (a 2048-step train batch, minibatches of
  64, 10 epochs, lr 3e-4, gamma 0.98, GAE lambda 0.95, clip 0.2, value-loss weight 0.5,
  gradient norm 0.5, no KL penalty, separate 64-64 tanh policy and value nets). RLlib learns
  in a normalised action space ([-1, 1] mapped onto the env's bounds) with a state-dependent
  log-std; the held-out evaluation maps the deterministic action the same way.
- Checkpoints: ``Algorithm.save_to_path`` into ``checkpoint_dir`` every
  ``checkpoint_every`` iterations and at the end, with the learning curve so far
  (``curve_rows.json``); ``resume`` restores both and trains on to ``timesteps``.
- Fault tolerance: ``restart_failed_env_runners``: a runner whose process dies is replaced
  and the iteration goes on with the others (``tests/test_train_rllib.py`` kills one).

Needs the ``distributed`` extra (``ray[rllib]``, torch, matplotlib).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from proprio_env.training.sb3 import (
    CURVE_SEED,
    HELD_OUT_BANDS,
    ROLLOUT_STEPS,
    SMOKE_ROLLOUT_STEPS,
    TrainConfig,
    evaluate,
    evaluate_policies,
    progress_line,
    quick_config,
    train_record,
    training_ranges,
    whole_rollouts,
    write_results,
)

DEFAULT_NUM_CPUS = 2
"""CPUs of the local Ray instance started when no ``address`` is given."""
CURVE_FILE = "curve_rows.json"
"""The learning curve so far, saved beside each checkpoint."""


@dataclass(frozen=True)
class RLlibOptions:
    """Where and how RLlib runs (the protocol itself is :class:`TrainConfig`)."""

    address: str | None = None
    """A running Ray cluster (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``); None
    starts a local instance with ``num_cpus``."""
    num_cpus: int = DEFAULT_NUM_CPUS
    num_env_runners: int = 1
    """Remote env runners (processes, one CPU each); 0 samples in the driver."""
    checkpoint_dir: Path | None = None
    checkpoint_every: int = 10
    """Checkpoint every this many iterations (one iteration = one PPO update)."""
    resume: bool = False
    """Restore ``checkpoint_dir`` and train on to ``TrainConfig.timesteps``."""

    def __post_init__(self) -> None:
        for name in ("num_cpus", "checkpoint_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}={value!r} must be a positive int")
        n = self.num_env_runners
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"num_env_runners={n!r} must be an int >= 0")
        if self.resume and self.checkpoint_dir is None:
            raise ValueError("resume=True needs a checkpoint_dir")
        if self.checkpoint_dir is not None and Path(self.checkpoint_dir).is_file():
            raise ValueError(f"checkpoint_dir={str(self.checkpoint_dir)!r} is a file, not a "
                             "folder")


def check_resume(config: TrainConfig, options: RLlibOptions) -> None:
    """With ``options.resume``: ValueError unless ``options.checkpoint_dir`` holds a
    checkpoint this module wrote (:func:`save_checkpoint`) for the same env. Runs before Ray
    is imported: a missing checkpoint was a FileNotFoundError, and another env's a torch
    size mismatch, after Ray had started."""
    if not options.resume:
        return
    where = Path(options.checkpoint_dir)
    if not where.is_dir():
        raise ValueError(f"checkpoint_dir={str(where)!r} does not exist: nothing to resume "
                         "(drop --resume to start a new run)")
    try:
        load_curve(where)
        env_id = json.loads((where / CURVE_FILE).read_text()).get("env_id")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"checkpoint_dir={str(where)!r} holds no checkpoint of a training "
                         f"run ({CURVE_FILE} unreadable: {exc!r})") from None
    if env_id is not None and env_id != config.env_id:
        raise ValueError(f"checkpoint_dir={str(where)!r} was trained on env {env_id!r}, not "
                         f"{config.env_id!r}: resume with --env {env_id}")


def rllib_env_id(env_id: str) -> str:
    """``env_id`` with the ``proprio_env:`` module prefix: Gymnasium imports ``proprio_env``
    (registering its ids) before looking the id up, in whichever process builds the env."""
    return env_id if ":" in env_id else f"proprio_env:{env_id}"


def runner_seed(seed: int, worker_index: int, num_envs: int) -> int:
    """The reset seed of runner ``worker_index``: its sub-env i gets this + i."""
    return int(seed) + int(worker_index) * int(num_envs)


def _env_runner_class():
    from ray.rllib.env.single_agent_env_runner import SingleAgentEnvRunner

    class ProprioEnvRunner(SingleAgentEnvRunner):
        """RLlib's single-agent env runner with disjoint sub-env seeds per runner."""

        def __init__(self, *, config, **kwargs):
            super().__init__(config=config, **kwargs)
            if config.seed is not None:
                # the first reset of the vector env uses _seed (sub-env i: _seed + i)
                self._seed = runner_seed(config.seed, self.worker_index,
                                         config.num_envs_per_env_runner)

    return ProprioEnvRunner


def _callbacks_class():
    from ray.rllib.callbacks.callbacks import RLlibCallback

    class TrainingError(RLlibCallback):
        """Per iteration: the sum of |angle error| over the env steps sampled (the curve's
        training error) and the env steps each runner sampled (``steps_by_runner``)."""

        def on_episode_step(self, *, episode, env_runner=None, metrics_logger=None,
                            **kwargs) -> None:
            info = episode.get_infos(-1)
            if metrics_logger is None or "angle_error_deg" not in info:
                return
            metrics_logger.log_value("train_abs_err_sum_deg",
                                     abs(float(info["angle_error_deg"])), reduce="sum")
            metrics_logger.log_value("train_abs_err_steps", 1, reduce="sum")
            if env_runner is not None:
                metrics_logger.log_value(("steps_by_runner", str(env_runner.worker_index)), 1,
                                         reduce="sum")

    return TrainingError


def ppo_config(config: TrainConfig, options: RLlibOptions, quick: bool = False):
    """RLlib's ``PPOConfig`` for ``config`` (see the module docstring for the settings)."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

    env_config = dict(config.env_kwargs(), target_ranges_deg=training_ranges())
    rollout = SMOKE_ROLLOUT_STEPS if quick else ROLLOUT_STEPS
    return (
        PPOConfig()
        .environment(rllib_env_id(config.env_id), env_config=env_config)
        .env_runners(num_env_runners=options.num_env_runners,
                     num_envs_per_env_runner=config.num_envs,
                     num_cpus_per_env_runner=1,
                     env_runner_cls=_env_runner_class(),
                     gym_env_vectorize_mode=_vectorize_mode(config.env_id),
                     rollout_fragment_length="auto")
        .training(train_batch_size_per_learner=rollout,
                  minibatch_size=32 if quick else 64,
                  num_epochs=2 if quick else 10,
                  lr=3e-4, gamma=0.98, lambda_=0.95, clip_param=0.2,
                  vf_loss_coeff=0.5, vf_clip_param=math.inf, entropy_coeff=0.0,
                  use_kl_loss=False, kl_coeff=0.0, grad_clip=0.5,
                  grad_clip_by="global_norm")
        .rl_module(model_config=DefaultModelConfig(fcnet_hiddens=[64, 64],
                                                   fcnet_activation="tanh",
                                                   vf_share_layers=False))
        .learners(num_learners=0)
        .callbacks(_callbacks_class())
        .fault_tolerance(restart_failed_env_runners=True,
                         max_num_env_runner_restarts=100,
                         delay_between_env_runner_restarts_s=1.0)
        .reporting(metrics_num_episodes_for_smoothing=20)
        .debugging(seed=config.seed, log_level="ERROR")
    )


def _vectorize_mode(env_id: str) -> str:
    import gymnasium as gym

    import proprio_env  # noqa: F401  (registers the envs)

    spec = gym.spec(env_id.split(":")[-1])
    return "vector_entry_point" if spec.vector_entry_point is not None else "sync"


def start_ray(options: RLlibOptions) -> None:
    """Connect to ``options.address`` or start a local instance of ``options.num_cpus``
    CPUs. Workers get this process's import path, so a source checkout (``PYTHONPATH=.``)
    runs the same code in every worker of a local cluster; nodes of a remote cluster need
    the package installed (docs/training.md)."""
    import ray

    if ray.is_initialized():
        return
    code_root = str(Path(__file__).resolve().parents[2])
    paths = [code_root] + [os.path.abspath(p) for p in
                           os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    runtime_env = {"env_vars": {"PYTHONPATH": os.pathsep.join(dict.fromkeys(paths)),
                                "OMP_NUM_THREADS": "1"}}
    kwargs: dict[str, Any] = dict(runtime_env=runtime_env, include_dashboard=False,
                                  log_to_driver=True, logging_level="ERROR")
    if options.address is None:
        ray.init(num_cpus=options.num_cpus, **kwargs)
    else:
        ray.init(address=options.address, **kwargs)


def build_algorithm(config: TrainConfig, options: RLlibOptions, quick: bool = False):
    """The PPO ``Algorithm``, restored from ``options.checkpoint_dir`` when ``resume``."""
    start_ray(options)
    algo = ppo_config(config, options, quick).build_algo()
    if options.resume:
        algo.restore_from_path(str(Path(options.checkpoint_dir).resolve()))
    return algo


def module_policy(module, action_space):
    """The RLModule's deterministic action as ``policy(obs, env) -> action``, mapped from
    RLlib's normalised [-1, 1] range onto ``action_space`` as its runners do."""
    import torch

    dist_cls = module.get_inference_action_dist_cls()
    low, high = action_space.low, action_space.high

    def policy(obs, env):
        with torch.no_grad():
            out = module.forward_inference(
                {"obs": torch.as_tensor(np.asarray(obs, dtype=np.float32)[None])})
        action = dist_cls.from_logits(out["action_dist_inputs"]).to_deterministic().sample()
        action = action.numpy()[0].astype(np.float64)
        return np.clip(low + (action + 1.0) * (high - low) / 2.0, low, high).astype(
            action_space.dtype)

    return policy


def env_steps(result: dict[str, Any]) -> int:
    """Env steps sampled so far (RLlib's lifetime counter in a ``train()`` result)."""
    runners = result.get("env_runners", {})
    steps = runners.get("num_env_steps_sampled_lifetime",
                        result.get("num_env_steps_sampled_lifetime", 0))
    return int(steps)


def steps_by_runner(result: dict[str, Any]) -> dict[int, int]:
    """Env steps each runner (by worker index) sampled in this iteration."""
    by_runner = result.get("env_runners", {}).get("steps_by_runner", {})
    return {int(k): int(v) for k, v in by_runner.items()}


def training_error(result: dict[str, Any]) -> float:
    """Mean |angle error| (deg) over the env steps sampled in this iteration."""
    runners = result.get("env_runners", {})
    total, n = runners.get("train_abs_err_sum_deg"), runners.get("train_abs_err_steps")
    return float(total) / float(n) if total is not None and n else math.nan


def save_checkpoint(algo, checkpoint_dir: Path, rows: list, elapsed_s: float,
                    env_id: str) -> None:
    """The algorithm (``save_to_path``) and the curve so far."""
    checkpoint_dir = Path(checkpoint_dir).resolve()
    algo.save_to_path(str(checkpoint_dir))
    write_curve(checkpoint_dir, rows, elapsed_s, env_id)


def write_curve(checkpoint_dir: Path, rows: list, elapsed_s: float, env_id: str) -> None:
    """The curve so far and the env it was trained on, beside a checkpoint
    (:func:`load_curve`, :func:`check_resume` read it)."""
    (Path(checkpoint_dir) / CURVE_FILE).write_text(json.dumps(
        {"rows": rows, "elapsed_s": elapsed_s, "env_id": env_id}))


def load_curve(checkpoint_dir: Path) -> tuple[list, float]:
    """The curve rows and training wall time saved with a checkpoint."""
    data = json.loads((Path(checkpoint_dir) / CURVE_FILE).read_text())
    return [tuple(r) for r in data["rows"]], float(data["elapsed_s"])


def run(out_dir: Path, quick: bool = False, config: TrainConfig | None = None,
        options: RLlibOptions | None = None, curve: Path | None = None) -> dict[str, Any]:
    """Train PPO with RLlib, evaluate it and the zero and random policies on the held-out
    targets; write the policy (``policy/``, an RLModule checkpoint:
    ``RLModule.from_checkpoint(out_dir / "policy")``), ``eval.json`` and ``curve.csv`` into
    ``out_dir`` and the learning curve to ``curve`` (default ``out_dir/curve.png``).
    ``quick``: tiny batches and evaluations (the smoke run). Returns what ``eval.json``
    holds."""
    config = TrainConfig() if config is None else config
    options = RLlibOptions() if options is None else options
    check_resume(config, options)  # before Ray starts
    import gymnasium as gym
    import ray
    import torch

    if quick:
        config = quick_config(config)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    curve_path = curve if curve is not None else out_dir / "curve.png"
    torch.set_num_threads(1)
    rows: list[tuple[int, float, float, float]] = []
    elapsed_before = 0.0
    if options.resume:
        rows, elapsed_before = load_curve(options.checkpoint_dir)

    algo = build_algorithm(config, options, quick)
    probe = gym.make(rllib_env_id(config.env_id))
    action_space = probe.action_space
    probe.close()
    where = options.address or f"local Ray, {options.num_cpus} CPUs"
    print(f"training PPO (RLlib, {options.num_env_runners} env runners x {config.num_envs} "
          f"envs, {where}) on {config.env_id} for up to {config.timesteps} steps or "
          f"{config.max_minutes:g} min (held-out bands {HELD_OUT_BANDS} deg)"
          + (f", resumed at {rows[-1][0]} steps" if rows else ""), flush=True)
    total = whole_rollouts(config.timesteps, SMOKE_ROLLOUT_STEPS if quick else ROLLOUT_STEPS)
    start = time.perf_counter()
    steps = rows[-1][0] if rows else 0
    next_eval = (steps // config.eval_every + 1) * config.eval_every if rows else 0
    iteration = 0
    restarts = 0
    try:
        while steps < config.timesteps:
            elapsed = elapsed_before + time.perf_counter() - start
            if elapsed >= config.max_minutes * 60:
                break
            result = algo.train()
            iteration += 1
            steps = env_steps(result)
            restarts = int(result.get("fault_tolerance", {}).get(
                "num_remote_worker_restarts", restarts))
            elapsed = elapsed_before + time.perf_counter() - start
            held = math.nan
            if steps >= next_eval:
                held = evaluate(module_policy(algo.get_module(), action_space),
                                config.env_id, config.env_kwargs(), config.curve_episodes,
                                seed=CURVE_SEED)["mean_abs_err_deg"]
                next_eval = steps + config.eval_every
            rows.append((steps, elapsed, training_error(result), held))
            print(progress_line(steps, total, elapsed, rows[-1][2], held), flush=True)
            if options.checkpoint_dir is not None and iteration % options.checkpoint_every == 0:
                save_checkpoint(algo, options.checkpoint_dir, rows, elapsed, config.env_id)
        train_s = elapsed_before + time.perf_counter() - start
        if options.checkpoint_dir is not None:
            save_checkpoint(algo, options.checkpoint_dir, rows, train_s, config.env_id)
        module = algo.get_module()
        module.save_to_path(str((out_dir / "policy").resolve()))
        results: dict[str, Any] = evaluate_policies(module_policy(module, action_space),
                                                    config)
    finally:
        algo.stop()
        if options.address is None:
            ray.shutdown()
    results["train"] = train_record(
        config, "rllib", steps, train_s, num_env_runners=options.num_env_runners,
        num_envs_per_runner=config.num_envs, address=options.address,
        num_cpus=options.num_cpus if options.address is None else None,
        env_runner_restarts=restarts, resumed=options.resume)
    write_results(out_dir, results, rows, curve_path, "rllib")
    return results


__all__ = ["RLlibOptions", "build_algorithm", "module_policy", "ppo_config", "rllib_env_id",
           "run", "runner_seed", "start_ray"]
