"""The one env core: ``n`` elbow envs written once over a leading axis of envs.

:class:`EnvCore` holds what an env step is: the checked settings, the model, the physics of
the n envs (:class:`~proprio_env.envs.physics.PhysicsBatch`), their afferent readout
(:class:`~proprio_env.envs.afferents.AfferentReadout`), targets, reward, observation,
``info`` and rendering. The single env (a ``gymnasium.Env``) is its n = 1 view, the native
vector env (a ``gymnasium.vector.VectorEnv``) its n view: the same arithmetic, so sub-env i
of a vector env and a single env fed the same seed and actions agree.

One env step of ``dt = 1 / control_hz`` seconds applies the actions, runs ``dt / timestep``
MuJoCo steps (2 ms each in ``elbow.xml``), collects the sensor samples of that interval
(one per physics step, or each encoder's own jittered ~500 Hz readings) and pushes them in
one block through the spindle chains, so the physics, the sensor and the spindles always end
the step at the same time. The observation is the chains' output at the end of the step.

What differs between the two ids (the actuators) is a :class:`Drive`.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import mujoco
import numpy as np
from gymnasium import spaces

from proprio_env import RATE_SCALE_PPS
from proprio_env.body.force_sense import TendonForceSense, max_forces_N
from proprio_env.body.length_fitting import fits_for_model
from proprio_env.body.model import JOINT, MUSCLES, model_path
from proprio_env.body.muscle_length import FibreLengths, muscle_geometry
from proprio_env.envs.afferents import SOURCES, AfferentReadout
from proprio_env.envs.arguments import (
    check_flag,
    check_instance,
    check_path,
    check_positive_int,
    check_ranges_deg,
    check_real,
    check_real_array,
    check_str,
    frames_per_step,
)
from proprio_env.envs.physics import PhysicsBatch, check_threads, load_sensed_model
from spindle.backends import BACKEND_CHOICES, DEFAULT_BACKEND, resolve_backend
from spindle.chain import ChainConfig
from spindle.chain.length_model import LengthFits, load_length_fits
from spindle.chain.sensor import AX12, EncoderParams

MUSCLE_GROUP_BIT = 1 << 1
SERVO_GROUP_BIT = 1 << 2
"""``model.opt.disableactuator`` bits: actuator group 1 = muscles, group 2 = servo."""

RENDER_MODES = ("rgb_array",)


class Drive:
    """What moves the elbow in one env id: its action space and how actions become MuJoCo
    controls, for n envs at once (subclasses: the muscles, the servo).

    Args:
        model: the env's model.
        joint_range_deg: the elbow's range (deg).
    """

    disabled_groups: ClassVar[int] = 0
    default_source: ClassVar[str] = "exact"
    default_control_cost_weight: ClassVar[float] = 0.0

    def __init__(self, model: mujoco.MjModel, joint_range_deg: tuple[float, float]) -> None:
        self.model = model
        self.joint_range_deg = joint_range_deg
        self.muscle_actuators = np.array([model.actuator(m).id for m in MUSCLES])

    def action_space(self) -> spaces.Box:
        raise NotImplementedError

    def write_controls(self, ctrl: np.ndarray, actions: np.ndarray) -> None:
        """Write the checked ``actions`` (n, action dim) into the controls ``ctrl`` (n, nu)."""
        raise NotImplementedError

    def rest_controls(self, ctrl: np.ndarray, angle_deg: float) -> None:
        """The controls (nu,) that hold the elbow at ``angle_deg`` at a reset."""
        ctrl[:] = 0.0

    def info(self, ctrl: np.ndarray, degrees: Any = np.degrees) -> dict[str, Any]:
        """This drive's own ``info`` entries from the controls: (n,) each from (n, nu), or
        numbers from one env's (nu,) with ``degrees=math.degrees``."""
        return {}

    def prepare_forces(self, model_file: Path) -> None:
        """Load what :meth:`tendon_forces_N` needs for the model in ``model_file`` (the
        muscles' force needs nothing more)."""

    def tendon_forces_N(self, actuator_force: np.ndarray, angle_rad: np.ndarray
                        ) -> np.ndarray:
        """The tendon forces (N, tension positive) of BRA and TRImed, (..., 2), from MuJoCo's
        ``actuator_force`` (..., nu) and the elbow angles (...): by default the muscles'
        own force (MuJoCo's muscle pulls with a negative force), active and passive."""
        return 0.0 - actuator_force[..., self.muscle_actuators]  # +0.0 for a zero force


# -- the arithmetic of a step, over a leading axis of envs --------------------------------------
def observation_size(include_fusimotor: bool, include_ib: bool) -> int:
    """Ia, II (4), the target (1), Ib (2, with ``include_ib``), gamma_s, gamma_d (4)."""
    return 5 + 2 * include_ib + 4 * include_fusimotor


def observations(sample: Any, target_rad: np.ndarray, include_fusimotor: bool,
                 ib_pps: np.ndarray | None = None) -> np.ndarray:
    """(n, :func:`observation_size`) float32 observations: a batch sample's (n, 2) rates
    (pps), the targets (n,) (rad) and, given, the Ib rates ``ib_pps`` (n, 2) (pps). The rates
    are divided in float64, then rounded once to float32."""
    obs = np.empty((target_rad.shape[0], observation_size(include_fusimotor,
                                                          ib_pps is not None)),
                   dtype=np.float32)
    # a float64 quotient assigned (rounded) into the float32 slice: the arithmetic of
    # np.divide(..., out=slice, casting="same_kind") in 9k instructions instead of 13k
    obs[:, 0:2] = sample.ia_pps / RATE_SCALE_PPS
    obs[:, 2:4] = sample.ii_pps / RATE_SCALE_PPS
    obs[:, 4] = target_rad
    g = 5
    if ib_pps is not None:
        obs[:, 5:7] = ib_pps / RATE_SCALE_PPS
        g = 7
    if include_fusimotor:
        obs[:, g:g + 2] = sample.gamma_static_pps / RATE_SCALE_PPS
        obs[:, g + 2:g + 4] = sample.gamma_dynamic_pps / RATE_SCALE_PPS
    # never observed (the chain rejects bad samples)
    if np.count_nonzero(np.isfinite(obs)) != obs.size:  # 7k instructions, a sum 9k
        bad = np.flatnonzero(~np.isfinite(obs).all(axis=1))
        if bad.size:
            i = int(bad[0])
            raise RuntimeError(f"non-finite observation {obs[i].tolist()} in env {i} (chain "
                               f"output t={sample.t_s[i]!r})")
    return obs


def rewards(angle_deg: Any, target_deg: Any, action_square: Any, distance_weight: float,
            control_weight: float) -> tuple[Any, Any]:
    """(reward_distance, reward_control): the distance term ``-w_dist |angle - target|``
    (rad) and the control cost ``-w_ctrl |a|^2`` from the squared norm of the action
    ``action_square``; of (n,) arrays, or of one env's floats (the same arithmetic: the single
    env's rewards as floats cost 10k instructions per step, as (1,) arrays 36k)."""
    distance = abs(angle_deg - target_deg) * (-distance_weight * (math.pi / 180.0))
    return distance, action_square * -control_weight


SCALAR_INFO = ("time_s", "angle_deg", "angular_velocity_deg_s", "target_deg",
               "angle_error_deg", "sensor_time_s", "reward_distance", "reward_control")
"""The ``info`` entries with one number per env: (n,) arrays in a vector env, floats in a
single env."""


def scalar_info(time_s: Any, angle_rad: Any, velocity_rad_s: Any, target_deg: Any,
                sensor_time_s: Any, distance: Any, control: Any,
                degrees: Any = np.degrees) -> dict[str, Any]:
    """The :data:`SCALAR_INFO` entries from the state's time, elbow angle and velocity, the
    targets, the chains' output time and the rewards: of (n,) arrays (``degrees`` numpy's)
    or of one env's floats (``math.degrees``: the same product)."""
    angle_deg = degrees(angle_rad)
    return {"time_s": time_s, "angle_deg": angle_deg,
            "angular_velocity_deg_s": degrees(velocity_rad_s), "target_deg": target_deg,
            "angle_error_deg": angle_deg - target_deg, "sensor_time_s": sensor_time_s,
            "reward_distance": distance, "reward_control": control}


MUSCLE_INFO = ("length_L0", "velocity_L0_s", "gamma_static_pps", "gamma_dynamic_pps",
               "ia_pps", "ii_pps")
"""The ``info`` entries with one number per muscle (``MUSCLES`` order): (n, 2) arrays, (2,)
in a single env."""
IB_INFO = ("force_N", "ib_pps")
"""The per-muscle ``info`` entries of the tendon organs (``include_ib``): the tendon force
(N) and Ib (pps) at the end of the step."""


def check_actions(actions: Any, shape: tuple[int, ...], clip: bool,
                  bounds: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``actions`` as float64 of ``shape`` inside the box ``bounds`` (low, high) (clipped if
    ``clip``), else ValueError naming the action and the box."""
    low, high = bounds
    # the common case in a few array operations: a float array of the right shape inside
    # the box (NaN fails both comparisons and takes the checked path below)
    if (isinstance(actions, np.ndarray) and actions.dtype.char in "fd"
            and actions.shape == shape):
        a = actions.astype(np.float64)
        # count_nonzero: 3k instructions, .all() 8k (its Python wrapper)
        if np.count_nonzero((a >= low) & (a <= high)) == a.size:
            return a
    a = check_real_array("action", actions)
    if a.shape != shape:
        raise ValueError(f"action has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action {a.tolist()} holds NaN or inf")
    if np.any(a < low) or np.any(a > high):
        if not clip:
            raise ValueError(
                f"action {a.tolist()} is outside the action box [{low.tolist()}, "
                f"{high.tolist()}] (pass clip_actions=True to clip instead)")
        a = np.clip(a, low, high)
    return a


def draw_from_ranges(rng: np.random.Generator, ranges: tuple[tuple[float, float], ...]
                     ) -> float:
    """A uniform draw from the union of the intervals ``ranges`` (by width; a zero-width
    interval is a fixed value)."""
    widths = np.array([hi - lo for lo, hi in ranges])
    if widths.sum() == 0:
        lo, _ = ranges[int(rng.integers(len(ranges)))]
        return lo
    k = int(rng.choice(len(ranges), p=widths / widths.sum()))
    lo, hi = ranges[k]
    return float(rng.uniform(lo, hi))


def make_renderer(model: mujoco.MjModel, width: int, height: int) -> mujoco.Renderer:
    """``mujoco.Renderer``, or a ``RuntimeError`` that names the GL backend tried and how to get
    a working one, in place of GLFW's warnings and MuJoCo's "OpenGL platform library" error."""
    backend = os.environ.get("MUJOCO_GL") or "glfw (MUJOCO_GL unset)"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            return mujoco.Renderer(model, height=height, width=width)
        except Exception as exc:
            cause = str(caught[0].message) if caught else str(exc)
            raise RuntimeError(
                f"render_mode='rgb_array' needs an OpenGL context, and MUJOCO_GL={backend} "
                f"could not create one ({cause[:200]}). Without a display, install Debian's "
                "libegl1 libegl-mesa0 libgl1-mesa-dri and run with MUJOCO_GL=egl (or "
                "MUJOCO_GL=osmesa with libosmesa6) set before mujoco is imported; with a "
                "display, MUJOCO_GL=glfw needs DISPLAY set.") from exc


def _camera() -> mujoco.MjvCamera:
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = (0.0, 0.0, 0.55)
    cam.distance = 0.9
    cam.azimuth = 90.0
    cam.elevation = -5.0
    return cam


class EnvCore:
    """``n`` elbow envs of one :class:`Drive`: settings, physics, sensing, chains, reward,
    observation, ``info`` and rendering (see the module docstring).

    Every argument is checked before anything is built (a refused one leaves nothing to
    close). The keyword arguments are the envs' (documented in
    :class:`~proprio_env.envs.ElbowReachEnv`); ``None`` for ``afferent_source`` and
    ``control_cost_weight`` takes the drive's default.
    """

    def __init__(self, drive: type[Drive], n: int = 1, num_threads: int = 1, *,
                 control_hz: float = 50.0, afferent_source: str | None = None,
                 backend: str = DEFAULT_BACKEND, chain_config: ChainConfig | None = None,
                 encoder_params: EncoderParams = AX12, include_fusimotor: bool = False,
                 include_ib: bool = False, target_ranges_deg: Any = ((15.0, 115.0),),
                 initial_angle_ranges_deg: Any = ((10.0, 120.0),),
                 distance_reward_weight: float = 1.0, control_cost_weight: float | None = None,
                 clip_actions: bool = False, xml_file: str | Path | None = None,
                 render_mode: str | None = None, width: int = 320, height: int = 320) -> None:
        self.n = check_positive_int("num_envs", n)
        num_threads = check_threads(num_threads)
        self.render_mode = (None if render_mode is None
                            else check_str("render_mode", render_mode, RENDER_MODES))
        control_hz = check_real("control_hz", control_hz, low=0.0, low_open=True)
        self.afferent_source = check_str(
            "afferent_source", drive.default_source if afferent_source is None
            else afferent_source, SOURCES)
        self.backend = resolve_backend(check_str("backend", backend, BACKEND_CHOICES))
        if chain_config is not None:
            check_instance("chain_config", chain_config, ChainConfig)
        check_instance("encoder_params", encoder_params, EncoderParams)
        self.include_fusimotor = check_flag("include_fusimotor", include_fusimotor)
        self.include_ib = check_flag("include_ib", include_ib)
        self.clip_actions = check_flag("clip_actions", clip_actions)
        self.distance_reward_weight = check_real("distance_reward_weight",
                                                 distance_reward_weight, low=0.0)
        self.control_cost_weight = check_real(
            "control_cost_weight", drive.default_control_cost_weight
            if control_cost_weight is None else control_cost_weight, low=0.0)
        model_file = model_path() if xml_file is None else check_path("xml_file", xml_file)
        # the model: the remaining checks need its buffers, time step and joint range
        self.model = model = load_sensed_model(model_file, forces=self.include_ib)
        self.width = check_positive_int("width", width, high=int(model.vis.global_.offwidth))
        self.height = check_positive_int("height", height,
                                         high=int(model.vis.global_.offheight))
        self.frame_skip = frames_per_step(control_hz, float(model.opt.timestep))
        self.control_hz = control_hz
        joint_id = model.joint(JOINT).id
        self.joint_range_deg = tuple(math.degrees(x) for x in model.jnt_range[joint_id])
        self.target_ranges_deg = check_ranges_deg("target_ranges_deg", target_ranges_deg,
                                                  self.joint_range_deg)
        self.initial_angle_ranges_deg = check_ranges_deg(
            "initial_angle_ranges_deg", initial_angle_ranges_deg, self.joint_range_deg)
        self._build(drive, model_file, chain_config, encoder_params, num_threads,
                    int(model.jnt_qposadr[joint_id]), int(model.jnt_dofadr[joint_id]))

    def _build(self, drive, model_file, chain_config, encoder_params, num_threads, qadr,
               vadr) -> None:
        """What the checked settings make: the drive, spaces, fits, chains, physics (last:
        its thread pool is the one thing to close)."""
        model, n = self.model, self.n
        self._qadr = qadr
        model.opt.disableactuator = drive.disabled_groups
        self.drive = drive(model, self.joint_range_deg)
        self.action_space = self.drive.action_space()
        self._action_bounds = (self.action_space.low.astype(np.float64),
                               self.action_space.high.astype(np.float64))
        n_obs = observation_size(self.include_fusimotor, self.include_ib)
        low, high = np.zeros(n_obs, np.float32), np.full(n_obs, np.inf, np.float32)
        high[4] = math.radians(self.joint_range_deg[1])
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self._fibre_lengths = FibreLengths(tuple(muscle_geometry(model, m) for m in MUSCLES))
        self._tendon_ids = np.array([model.tendon(m).id for m in MUSCLES])
        config = replace(ChainConfig() if chain_config is None else chain_config,
                         backend=self.backend)
        self.length_fits: LengthFits = (
            load_length_fits(config.fits_path, model_xml=model_file)
            if config.fits_path is not None else fits_for_model(model_file, model))
        self.afferents = AfferentReadout(self.afferent_source, config, encoder_params,
                                         self.length_fits, step_s=self.dt, n=n)
        self.target_deg = np.full(n, 0.5 * sum(self.joint_range_deg))
        self._target_rad = np.radians(self.target_deg)
        self.sample = None  # the chains' latest output, after the first reset
        self._angle_deg = None  # (n, frames) elbow angles of the last step (deg)
        self.tendon_organs = None
        if self.include_ib:
            self.drive.prepare_forces(model_file)
            self.tendon_organs = TendonForceSense(
                n, float(model.opt.timestep), max_forces_N(model, self.drive.muscle_actuators),
                self.backend)
        self._renderer: mujoco.Renderer | None = None
        self._render_data: mujoco.MjData | None = None
        # the first scratch data is the single env's `data`: it holds the state after a step
        self.data = mujoco.MjData(model)
        extra = [mujoco.MjData(model) for _ in range(num_threads - 1)]
        self.physics = PhysicsBatch(model, n, self.frame_skip, num_threads,
                                    scratch=[self.data, *extra], qadr=qadr, vadr=vadr)

    @property
    def dt(self) -> float:
        """Duration of one env step (s)."""
        return self.frame_skip * float(self.model.opt.timestep)

    # -- the step ---------------------------------------------------------------------------
    def check_actions(self, actions: Any, shape: tuple[int, ...]) -> np.ndarray:
        """The actions of ``shape`` checked (see :func:`check_actions`)."""
        return check_actions(actions, shape, self.clip_actions, self._action_bounds)

    def step(self, actions: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
        """Advance every env under its checked ``actions`` (n, action dim); the envs with
        ``active`` False (None: all active) push no sensor sample and may diverge unchecked
        (they are about to be reset). Returns the samples pushed per env (n,); the physics
        state, :attr:`sample` and the elbow angles of the step (for :meth:`rewards`) hold the
        step's end."""
        physics = self.physics
        self.drive.write_controls(physics.ctrl, actions)
        physics.step()
        qv = physics.state[:, physics.qpos_qvel]
        if np.count_nonzero(np.isfinite(qv)) != qv.size:  # 7k instructions, a sum 9k
            bad = ~np.isfinite(qv).all(axis=1) & (True if active is None else active)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise RuntimeError(f"physics diverged in env {i}: elbow angle {qv[i, 0]!r} "
                                   f"rad, velocity {qv[i, 1]!r} rad/s")
        self._angle_deg = angle_deg = np.degrees(physics.angle_rad())
        lengths = None
        if self.afferent_source == "exact":
            lengths = self._fibre_lengths(physics.tendon_lengths_m(self.data))
        self.sample, pushed = self.afferents.push(physics.time_s(), angle_deg, lengths, active)
        if self.tendon_organs is not None:
            self.tendon_organs.step(self.drive.tendon_forces_N(
                physics.actuator_forces(), physics.angle_rad()))
        return pushed

    def rewards(self, actions: np.ndarray, env: int | None = None) -> tuple[Any, Any]:
        """(reward_distance, reward_control) of the last :meth:`step` under ``actions``
        (n, action dim): (n,) arrays, or env ``env``'s floats."""
        square = np.vecdot(actions, actions)
        end_deg = self._angle_deg[:, -1]
        if env is None:
            return rewards(end_deg, self.target_deg, square, self.distance_reward_weight,
                           self.control_cost_weight)
        return rewards(end_deg.item(env), self.target_deg.item(env), square.item(env),
                       self.distance_reward_weight, self.control_cost_weight)

    def observations(self) -> np.ndarray:
        """(n, 5) or (n, 9) float32: the chains' latest output and the targets."""
        organs = self.tendon_organs
        return observations(self.sample, self._target_rad, self.include_fusimotor,
                            None if organs is None else organs.ib_pps)

    def info(self, pushed: np.ndarray, distance: Any, control: Any,
             env: int | None = None) -> dict[str, Any]:
        """The raw signals of a step (copies): :data:`SCALAR_INFO`, :data:`MUSCLE_INFO`,
        ``sensor_samples`` (``pushed``, (n,)) and the drive's own entries, of every env ((n,)
        and (n, 2) arrays; ``distance``, ``control`` (n,)) or, given ``env``, of that one
        (numbers and (2,) arrays; ``distance``, ``control`` its numbers)."""
        physics, sample = self.physics, self.sample
        state = physics.state
        columns = (state[:, 0], state[:, physics.qpos_index], state[:, physics.qvel_index],
                   self.target_deg, sample.t_s)
        muscles = {name: getattr(sample, name) for name in MUSCLE_INFO}
        if self.tendon_organs is not None:
            muscles["force_N"] = self.tendon_organs.force_N
            muscles["ib_pps"] = self.tendon_organs.ib_pps
        if env is None:
            info = {name: np.array(x) for name, x in scalar_info(
                *columns, distance, control, np.degrees).items()}
            info.update({name: np.array(x) for name, x in
                         self.drive.info(physics.ctrl, np.degrees).items()})
            info.update({name: np.array(x) for name, x in muscles.items()})
            info["sensor_samples"] = pushed
            return info
        # one env: its numbers as Python floats through the same arithmetic (the single
        # env's info took 73k instructions per step as (1,) arrays, 29k before issue 23)
        info = scalar_info(*(x.item(env) for x in columns), distance, control, math.degrees)
        info.update(self.drive.info(physics.ctrl[env], math.degrees))
        for name, x in muscles.items():
            info[name] = x[env].copy()
        info["sensor_samples"] = pushed.item(env)
        return info

    # -- resets -----------------------------------------------------------------------------
    def reset(self, envs: np.ndarray, rngs: list[np.random.Generator],
              target_deg: np.ndarray | None = None, angle_deg: np.ndarray | None = None
              ) -> None:
        """Reset the envs ``envs`` (m,) with their generators ``rngs``: target and initial
        angle fixed by ``target_deg`` / ``angle_deg`` (m,) (checked) or drawn (the target
        first), physics at rest, chains, encoders. Atomic: if anything raises, the envs and
        the generators are as they were."""
        m, data, physics = envs.size, self.data, self.physics
        saved = (physics.state[envs], physics.ctrl[envs],
                 [rng.bit_generator.state for rng in rngs])
        try:
            targets, angles = np.empty(m), np.empty(m)
            lengths, times = np.empty((m, 2)), np.empty(m)
            forces = np.zeros((m, 2))
            for j, (i, rng) in enumerate(zip(envs.tolist(), rngs, strict=True)):
                targets[j] = (draw_from_ranges(rng, self.target_ranges_deg)
                              if target_deg is None else target_deg[j])
                angles[j] = (draw_from_ranges(rng, self.initial_angle_ranges_deg)
                             if angle_deg is None else angle_deg[j])
                mujoco.mj_resetData(self.model, data)
                data.qpos[self._qadr] = math.radians(angles[j])
                self.drive.rest_controls(data.ctrl, float(angles[j]))
                mujoco.mj_forward(self.model, data)
                lengths[j] = self._fibre_lengths(data.ten_length[self._tendon_ids])
                times[j] = data.time
                if self.tendon_organs is not None:
                    forces[j] = self.drive.tendon_forces_N(data.actuator_force,
                                                           data.qpos[self._qadr])
                physics.store(i, data)
            self.afferents.reset(envs, times, angles, lengths, rngs)
            if self.tendon_organs is not None:
                self.tendon_organs.reset(envs, forces)
        except BaseException:
            physics.state[envs], physics.ctrl[envs] = saved[:2]
            for rng, state in zip(rngs, saved[2], strict=True):
                rng.bit_generator.state = state
            raise
        self.target_deg[envs] = targets
        self._target_rad = np.radians(self.target_deg)
        self.sample = self.afferents.chain.last

    # -- rendering and closing ----------------------------------------------------------------
    def render(self, i: int = 0) -> np.ndarray | None:
        """Env ``i``'s image (``render_mode="rgb_array"``), else ``None``; drawn from its own
        data, so rendering changes nothing a step reads."""
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = make_renderer(self.model, self.width, self.height)
            self._render_data = mujoco.MjData(self.model)
        self.physics.load(i, self._render_data)
        self._renderer.update_scene(self._render_data, camera=_camera())
        return self._renderer.render()

    def close(self) -> None:
        """Close the renderer and stop the physics' thread pool (one-thread physics has none
        and keeps stepping, as a Gymnasium env may after ``close``)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self.physics.num_threads > 1:
            self.physics.close()

    def __getstate__(self) -> dict[str, Any]:
        """Everything but the GL renderer (pickling, deep copies)."""
        state = self.__dict__.copy()
        state["_renderer"] = state["_render_data"] = None
        return state


SHOWN_SETTINGS = {
    "backend": "The chains' backend, resolved: 'numpy' or 'c'.",
    "afferent_source": "One of SOURCES.",
    "afferents": "The AfferentReadout: chains (``.chain``), encoders (``.encoders``).",
    "model": "The MuJoCo model (with the tendon-length sensors).",
    "length_fits": "The length fits of the model.",
    "frame_skip": "Physics steps per env step.",
    "control_hz": "Env steps per second.",
    "dt": "Duration of one env step (s).",
    "joint_range_deg": "The elbow's range (deg).",
    "target_ranges_deg": "Where targets are drawn (deg).",
    "initial_angle_ranges_deg": "Where initial angles are drawn (deg).",
    "include_fusimotor": "gamma_s, gamma_d observed.",
    "include_ib": "Ib (tendon organs) observed.",
    "tendon_organs": "The TendonForceSense (``include_ib``), else None.",
    "clip_actions": "Out-of-box actions clipped (not refused).",
    "distance_reward_weight": "w_dist.",
    "control_cost_weight": "w_ctrl.",
    "width": "Rendered image width (pixels).",
    "height": "Rendered image height (pixels).",
}
"""The settings both env classes show (read-only) from their :class:`EnvCore`."""


class CoreSettings:
    """What the single and the vector env show of their :class:`EnvCore` (``self.core``):
    :data:`SHOWN_SETTINGS`, read from it, stored once there."""

    core: EnvCore

    @property
    def disabled_groups(self) -> int:
        """The ``model.opt.disableactuator`` bits of this env's drive."""
        return self.core.drive.disabled_groups


def _from_core(name: str, doc: str) -> property:
    return property(lambda self: getattr(self.core, name), doc=doc)


for _name, _doc in SHOWN_SETTINGS.items():
    setattr(CoreSettings, _name, _from_core(_name, _doc))
