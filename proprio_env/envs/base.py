"""What the two elbow envs share: physics, timing, targets, afferent observation, rendering.

One env step of ``dt = 1 / control_hz`` seconds applies the action, runs ``dt / timestep``
MuJoCo steps (2 ms each in ``elbow.xml``), collects the sensor samples of that interval
(one per physics step, or the encoder's own jittered ~500 Hz readings) and pushes them in one
block through the spindle chain, so the physics, the sensor and the spindles always end the
step at the same time. The observation is the chain's output at the end of the step.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from proprio_env.envs.afferents import SOURCES, AfferentReadout
from proprio_env.envs.arguments import (
    check_flag,
    check_instance,
    check_path,
    check_positive_int,
    check_real,
    check_real_array,
    check_str,
)
from proprio_env.envs.physics import PhysicsBatch, load_sensed_model
from proprio_env.length_fitting import fits_for_model
from proprio_env.model import JOINT, MUSCLES, model_path
from proprio_env.muscle_length import FibreLengths, muscle_geometry
from spindle.chain import BACKEND_CHOICES, ArmSample, ChainConfig, resolve_backend
from spindle.chain.length_model import LengthFits, load_length_fits
from spindle.chain.sensor import AX12, EncoderParams

RATE_SCALE_PPS = 100.0
"""Afferent and fusimotor rates enter the observation divided by this (pps)."""

MIN_CONTROL_HZ = 0.1
"""Slowest control rate (Hz): an env step of at most 10 s bounds the work and the buffers of
one step."""

MUSCLE_GROUP_BIT = 1 << 1
SERVO_GROUP_BIT = 1 << 2
"""``model.opt.disableactuator`` bits: actuator group 1 = muscles, group 2 = servo."""

def observations(ia_pps: np.ndarray, ii_pps: np.ndarray, gamma_static_pps: np.ndarray,
                 gamma_dynamic_pps: np.ndarray, target_rad: np.ndarray | float,
                 include_fusimotor: bool) -> np.ndarray:
    """(..., 5) or (..., 9) float32 observations from (..., 2) rates (pps) and targets (rad)
    of shape (...): one env (2,) and a float, or n envs (n, 2) and (n,). The rates are
    divided in float64, then rounded once to float32."""
    obs = np.empty((*ia_pps.shape[:-1], 9 if include_fusimotor else 5), dtype=np.float32)
    np.divide(ia_pps, RATE_SCALE_PPS, out=obs[..., 0:2], casting="same_kind")
    np.divide(ii_pps, RATE_SCALE_PPS, out=obs[..., 2:4], casting="same_kind")
    obs[..., 4] = target_rad
    if include_fusimotor:
        np.divide(gamma_static_pps, RATE_SCALE_PPS, out=obs[..., 5:7], casting="same_kind")
        np.divide(gamma_dynamic_pps, RATE_SCALE_PPS, out=obs[..., 7:9], casting="same_kind")
    return obs


def check_observations(obs: np.ndarray, t_s: Any) -> None:
    """RuntimeError naming the env if an observation is not finite (never observed); one
    observation (k,) or n of them (n, k)."""
    if np.isfinite(obs).all():
        return
    if obs.ndim == 1:
        raise RuntimeError(f"non-finite observation {obs.tolist()} (chain output t={t_s!r})")
    i = int(np.flatnonzero(~np.isfinite(obs).all(axis=1))[0])
    raise RuntimeError(f"non-finite observation {obs[i].tolist()} in env {i} (chain "
                       f"output t={t_s[i]!r})")


def rewards(angle_deg: np.ndarray, target_deg: np.ndarray, actions: np.ndarray,
            distance_weight: float, control_weight: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(reward, reward_distance, reward_control), each (n,): the distance term
    ``-w_dist |angle - target|`` (rad) and the control cost ``-w_ctrl |a|^2``."""
    distance = -distance_weight * np.abs(np.radians(angle_deg - target_deg))
    control = -control_weight * np.einsum("ij,ij->i", actions, actions)
    return distance + control, distance, control


def step_info(sample: Any, time_s: Any, angle_deg: Any, velocity_deg_s: Any, target_deg: Any,
              pushed: Any, reward_distance: Any, reward_control: Any) -> dict[str, Any]:
    """The raw signals of a step (``info``), scalars or arrays alike; ``sample`` is an
    :class:`~spindle.chain.ArmSample` or a batch of them (its arrays are copied: the chain
    may share them with its state)."""
    return {
        "time_s": time_s,
        "angle_deg": angle_deg,
        "angular_velocity_deg_s": velocity_deg_s,
        "target_deg": target_deg,
        "angle_error_deg": angle_deg - target_deg,
        "length_L0": np.array(sample.length_L0),
        "velocity_L0_s": np.array(sample.velocity_L0_s),
        "gamma_static_pps": np.array(sample.gamma_static_pps),
        "gamma_dynamic_pps": np.array(sample.gamma_dynamic_pps),
        "ia_pps": np.array(sample.ia_pps),
        "ii_pps": np.array(sample.ii_pps),
        "sensor_time_s": sample.t_s,
        "sensor_samples": pushed,
        "reward_distance": reward_distance,
        "reward_control": reward_control,
    }


def check_actions(actions: Any, space: spaces.Box, shape: tuple[int, ...], clip: bool,
                  bounds: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``actions`` as float64 of ``shape`` inside ``space`` (clipped if ``clip``), else
    ValueError naming the action and the box. ``bounds``: the box's (low, high) as float64,
    if the caller keeps them."""
    low, high = ((space.low.astype(np.float64), space.high.astype(np.float64))
                 if bounds is None else bounds)
    # the common case in a few array operations: a float array of the right shape inside
    # the box (NaN fails both comparisons and takes the checked path below)
    if (isinstance(actions, np.ndarray) and actions.dtype.char in "fd"
            and actions.shape == shape):
        a = actions.astype(np.float64)
        if ((a >= low) & (a <= high)).all():
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


def check_ranges_deg(name: str, ranges: Any, limits_deg: tuple[float, float]
                     ) -> tuple[tuple[float, float], ...]:
    """``ranges`` as a tuple of (low, high) intervals (deg) inside ``limits_deg``; the bounds
    must be real numbers (:func:`~proprio_env.envs.arguments.check_real`)."""
    try:
        pairs = [tuple(pair) for pair in ranges]
    except TypeError as exc:
        raise ValueError(f"{name}={ranges!r} must be a sequence of (low, high) pairs "
                         "in degrees") from exc
    if isinstance(ranges, str | bytes) or any(len(pair) != 2 for pair in pairs):
        raise ValueError(f"{name}={ranges!r} must be a sequence of (low, high) pairs "
                         "in degrees")
    out = tuple((check_real(f"{name} low", lo), check_real(f"{name} high", hi))
                for lo, hi in pairs)
    if not out:
        raise ValueError(f"{name} must hold at least one (low, high) interval")
    lo_lim, hi_lim = limits_deg
    for lo, hi in out:
        if not (lo_lim <= lo <= hi <= hi_lim):
            raise ValueError(f"{name} interval ({lo!r}, {hi!r}) must satisfy "
                             f"{lo_lim:g} <= low <= high <= {hi_lim:g} deg")
    return out


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


class ElbowProprioEnv(gym.Env):
    """Base class; see :class:`~proprio_env.envs.ElbowReachEnv` and
    :class:`~proprio_env.envs.ProsthesisElbowEnv` for the documented envs."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 50}

    #: set by subclasses
    disabled_groups: ClassVar[int] = 0
    default_source: ClassVar[str] = "exact"

    def __init__(
        self,
        *,
        control_hz: float = 50.0,
        afferent_source: str | None = None,
        backend: str = "auto",
        chain_config: ChainConfig | None = None,
        encoder_params: EncoderParams = AX12,
        include_fusimotor: bool = False,
        target_ranges_deg: Any = ((15.0, 115.0),),
        initial_angle_ranges_deg: Any = ((10.0, 120.0),),
        distance_reward_weight: float = 1.0,
        control_cost_weight: float = 0.0,
        clip_actions: bool = False,
        xml_file: str | Path | None = None,
        render_mode: str | None = None,
        width: int = 320,
        height: int = 320,
    ) -> None:
        # Every argument is checked before anything is built (arguments.py: no bool as a
        # number, no string as a bool, no complex; numpy scalars welcome).
        control_hz, source, backend, model_file = self._check_arguments(
            render_mode, control_hz, afferent_source, backend, chain_config, encoder_params,
            include_fusimotor, clip_actions, distance_reward_weight, control_cost_weight,
            xml_file)
        self._load_model(model_file, width, height, control_hz)
        self.target_ranges_deg = check_ranges_deg("target_ranges_deg", target_ranges_deg,
                                                  self.joint_range_deg)
        self.initial_angle_ranges_deg = check_ranges_deg(
            "initial_angle_ranges_deg", initial_angle_ranges_deg, self.joint_range_deg)
        self._geometries = tuple(muscle_geometry(self.model, m) for m in MUSCLES)
        self._fibre_lengths_of = FibreLengths(self._geometries)
        self._tendon_ids = np.array([self.model.tendon(m).id for m in MUSCLES])
        config = replace(ChainConfig() if chain_config is None else chain_config,
                         backend=backend)
        self.length_fits = self._length_fits(model_file, config)
        self.afferents = AfferentReadout(source, config, encoder_params, self.length_fits,
                                         step_s=self.dt)
        self.afferent_source = source
        self.backend = backend
        self.observation_space = self._make_observation_space()
        self.action_space = self._make_action_space()
        self._action_bounds = (self.action_space.low.astype(np.float64),
                               self.action_space.high.astype(np.float64))

        self._target_deg = 0.5 * sum(self.joint_range_deg)
        self._target_rad = math.radians(self._target_deg)
        self._sample: ArmSample | None = None
        self._renderer: mujoco.Renderer | None = None
        self._physics = PhysicsBatch(self.model, 1, self.frame_skip, scratch=[self.data],
                                     qadr=self._qadr, vadr=self._vadr)

    def _check_arguments(self, render_mode, control_hz, afferent_source, backend, chain_config,
                         encoder_params, include_fusimotor, clip_actions,
                         distance_reward_weight, control_cost_weight, xml_file):
        """Check the arguments that need no model and keep the plain settings; returns the
        checked (control_hz, afferent source, backend, model file)."""
        if render_mode is not None:
            check_str("render_mode", render_mode, tuple(self.metadata["render_modes"]))
        self.render_mode = render_mode
        control_hz = check_real("control_hz", control_hz, low=0.0, low_open=True)
        source = check_str("afferent_source",
                           self.default_source if afferent_source is None else afferent_source,
                           SOURCES)
        backend = resolve_backend(check_str("backend", backend, BACKEND_CHOICES))
        if chain_config is not None:
            check_instance("chain_config", chain_config, ChainConfig)
        check_instance("encoder_params", encoder_params, EncoderParams)
        self.include_fusimotor = check_flag("include_fusimotor", include_fusimotor)
        self.clip_actions = check_flag("clip_actions", clip_actions)
        self.distance_reward_weight = check_real("distance_reward_weight",
                                                 distance_reward_weight, low=0.0)
        self.control_cost_weight = check_real("control_cost_weight", control_cost_weight,
                                              low=0.0)
        model_file = model_path() if xml_file is None else check_path("xml_file", xml_file)
        return control_hz, source, backend, model_file

    def _load_model(self, model_file: Path, width, height, control_hz: float) -> None:
        """The MuJoCo model and data, the render size, the physics steps per env step and
        the elbow joint's addresses and range."""
        self.model = load_sensed_model(model_file)
        self.width = check_positive_int("width", width,
                                        high=int(self.model.vis.global_.offwidth))
        self.height = check_positive_int("height", height,
                                         high=int(self.model.vis.global_.offheight))
        self.model.opt.disableactuator = self.disabled_groups
        self.data = mujoco.MjData(self.model)
        self.frame_skip = self._frames_per_step(control_hz, float(self.model.opt.timestep))
        self.control_hz = control_hz
        self.metadata = {**self.metadata, "render_fps": self.control_hz}
        joint_id = self.model.joint(JOINT).id
        self._qadr = int(self.model.jnt_qposadr[joint_id])
        self._vadr = int(self.model.jnt_dofadr[joint_id])
        lo, hi = (math.degrees(x) for x in self.model.jnt_range[joint_id])
        self.joint_range_deg = (lo, hi)

    @staticmethod
    def _frames_per_step(control_hz: float, timestep: float) -> int:
        """Physics steps of ``timestep`` per env step of 1/control_hz (a whole number)."""
        if not MIN_CONTROL_HZ <= control_hz <= 1.0 / timestep:
            raise ValueError(f"control_hz={control_hz!r} must lie in [{MIN_CONTROL_HZ:g}, "
                             f"{1.0 / timestep:g}] Hz (one physics step of {timestep:g} s)")
        frames = round(1.0 / (control_hz * timestep))
        if abs(frames * timestep * control_hz - 1.0) > 1e-9:
            raise ValueError(
                f"control_hz={control_hz!r}: the env step 1/control_hz must be a whole number "
                f"of physics steps of {timestep:g} s (e.g. 50, 100, 125, 250, 500 Hz)")
        return frames

    def _make_observation_space(self) -> spaces.Box:
        n_obs = 5 + (4 if self.include_fusimotor else 0)
        low = np.zeros(n_obs, dtype=np.float32)
        high = np.full(n_obs, np.inf, dtype=np.float32)
        low[4], high[4] = 0.0, math.radians(self.joint_range_deg[1])
        return spaces.Box(low, high, dtype=np.float32)

    # -- subclass hooks ---------------------------------------------------------------------
    def _make_action_space(self) -> spaces.Box:
        raise NotImplementedError

    # -- gymnasium API ----------------------------------------------------------------------
    @property
    def dt(self) -> float:
        """Duration of one env step (s)."""
        return self.frame_skip * float(self.model.opt.timestep)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode. ``options`` may fix ``"target_deg"`` and ``"angle_deg"``
        (elbow flexion, deg, inside the joint range) instead of drawing them."""
        super().reset(seed=seed)
        rng = self.np_random
        target, angle = self.draw_start(rng, {} if options is None else dict(options))
        self._target_deg = target
        self._target_rad = math.radians(target)
        length = self.reset_physics(self.data, angle)
        self._physics.store(0, self.data)
        self._sample = self.afferents.reset(self.data.time, angle, length, rng)
        return self._observation(), self._info(0, 0.0, 0.0)

    def step(self, action):
        # Python work per step counts against the physics (~10 mj_step): scalars stay
        # Python floats, arrays come straight from the physics buffers.
        if self._sample is None:
            raise RuntimeError("call reset() before step()")
        action = self._check_action(action)
        physics = self._physics
        self.write_controls(physics.ctrl, action[None, :])
        physics.step()
        d = self.data
        q, v = float(d.qpos[self._qadr]), float(d.qvel[self._vadr])
        if not (math.isfinite(q) and math.isfinite(v)):
            raise RuntimeError(f"physics diverged: elbow angle {q!r} rad, velocity {v!r} rad/s")
        lengths = None
        if self.afferent_source == "exact":
            lengths = self._fibre_lengths(physics.tendon_lengths_m(d)[0])
        self._sample, pushed = self.afferents.push(
            physics.time_s()[0], np.degrees(physics.angle_rad()[0]), lengths)
        obs = self._observation()
        angle_deg = math.degrees(q)
        # the same arithmetic as rewards() for the vector env
        reward_distance = -self.distance_reward_weight * abs(
            math.radians(angle_deg - self._target_deg))
        reward_control = -self.control_cost_weight * float(action @ action)
        reward = reward_distance + reward_control
        info = step_info(self._sample, float(d.time), angle_deg, math.degrees(v),
                         self._target_deg, pushed, reward_distance, reward_control)
        return obs, reward, False, False, self._add_info(info)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = make_renderer(self.model, self.width, self.height)
        self._renderer.update_scene(self.data, camera=self._camera())
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # -- pickling: everything but the GL renderer ---------------------------------------------
    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_renderer"] = None
        return state

    # -- state readouts -----------------------------------------------------------------------
    @property
    def angle_deg(self) -> float:
        """Elbow flexion (deg, 0 = straight)."""
        return math.degrees(float(self.data.qpos[self._qadr]))

    @property
    def target_deg(self) -> float:
        """This episode's target elbow flexion (deg)."""
        return self._target_deg

    # -- helpers ------------------------------------------------------------------------------
    def reset_physics(self, data: mujoco.MjData, angle_deg: float) -> np.ndarray:
        """Put ``data`` at rest at ``angle_deg`` with this env's reset controls; return the
        fibre lengths there (2,) (L0)."""
        m = self.model
        mujoco.mj_resetData(m, data)
        data.qpos[self._qadr] = math.radians(angle_deg)
        self._reset_controls(data, angle_deg)
        mujoco.mj_forward(m, data)
        return self._fibre_lengths(data.ten_length[self._tendon_ids][None, :])[0]

    def _reset_controls(self, data: mujoco.MjData, angle_deg: float) -> None:
        data.ctrl[:] = 0.0

    def write_controls(self, ctrl: np.ndarray, actions: np.ndarray) -> None:
        """Write the (checked) ``actions`` (n, action dim) into the controls ``ctrl``
        (n, nu)."""
        raise NotImplementedError

    def draw_start(self, rng: np.random.Generator, options: dict[str, Any]
                   ) -> tuple[float, float]:
        """(target, initial angle) in deg: fixed by ``options`` or drawn from ``rng`` (the
        target first)."""
        unknown = set(options) - {"target_deg", "angle_deg"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; "
                             "known: 'target_deg', 'angle_deg'")
        target = (self._fixed_angle("target_deg", options["target_deg"])
                  if "target_deg" in options else draw_from_ranges(rng, self.target_ranges_deg))
        angle = (self._fixed_angle("angle_deg", options["angle_deg"])
                 if "angle_deg" in options
                 else draw_from_ranges(rng, self.initial_angle_ranges_deg))
        return target, angle

    def _camera(self) -> mujoco.MjvCamera:
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = (0.0, 0.0, 0.55)
        cam.distance = 0.9
        cam.azimuth = 90.0
        cam.elevation = -5.0
        return cam

    def _fixed_angle(self, name: str, value: Any) -> float:
        lo, hi = self.joint_range_deg
        x = check_real(name, value)
        if not lo <= x <= hi:
            raise ValueError(f"{name}={value!r} must be finite and within the joint range "
                             f"[{lo:g}, {hi:g}] deg")
        return x

    def _fibre_lengths(self, mtu_m: np.ndarray) -> np.ndarray:
        return self._fibre_lengths_of(mtu_m)

    def _length_fits(self, model_file: Path, config: ChainConfig) -> LengthFits:
        """The fits of this env's model: ``config.fits_path`` checked against the model's
        sha256 if given, else :func:`~proprio_env.length_fitting.fits_for_model`."""
        if config.fits_path is not None:
            return load_length_fits(config.fits_path, model_xml=model_file)
        return fits_for_model(model_file, self.model)

    def _check_action(self, action: Any) -> np.ndarray:
        return check_actions(action, self.action_space, self.action_space.shape,
                             self.clip_actions, self._action_bounds)

    def _observation(self) -> np.ndarray:
        s = self._sample
        obs = observations(s.ia_pps, s.ii_pps, s.gamma_static_pps, s.gamma_dynamic_pps,
                           self._target_rad, self.include_fusimotor)
        check_observations(obs, s.t_s)
        return obs

    def _info(self, pushed: int, reward_distance: float, reward_control: float
              ) -> dict[str, Any]:
        return self._add_info(step_info(
            self._sample, float(self.data.time), self.angle_deg,
            math.degrees(float(self.data.qvel[self._vadr])), self._target_deg, int(pushed),
            reward_distance, reward_control))

    def _add_info(self, info: dict[str, Any]) -> dict[str, Any]:
        """Subclass hook: this env's own entries added to ``info``."""
        return info
