# ruff: noqa: E501  (Gymnasium-style markdown tables in the class docstring)
"""``proprio_env/ElbowReach-v0`` / ``-v1``: the muscle-driven elbow, felt only through its
spindles (and, in v1, its tendon organs)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces

from proprio_env.body.model import MUSCLES
from proprio_env.envs.base import ElbowProprioEnv
from proprio_env.envs.core import SERVO_GROUP_BIT, Drive


class MuscleDrive(Drive):
    """BRA and TRImed excitations (``Box(0, 1, (2,))``), the servo disabled."""

    disabled_groups: ClassVar[int] = SERVO_GROUP_BIT
    default_source: ClassVar[str] = "exact"
    default_control_cost_weight: ClassVar[float] = 0.05

    def __init__(self, model: Any, joint_range_deg: tuple[float, float]) -> None:
        super().__init__(model, joint_range_deg)
        self._muscle_ids = np.array([model.actuator(m).id for m in MUSCLES])

    def action_space(self) -> spaces.Box:
        return spaces.Box(0.0, 1.0, (2,), dtype=np.float32)

    def write_controls(self, ctrl: np.ndarray, actions: np.ndarray) -> None:
        ctrl[:, self._muscle_ids] = actions


class ElbowReachEnv(ElbowProprioEnv):
    r"""
    ## Description
    The Arm26 elbow (OpenSim's Arm26, Holzbaur et al. 2005; ``models/elbow.xml``) moved by
    two MuJoCo muscles, the brachialis (BRA, flexor) and the medial head of the triceps
    (TRImed, extensor), under gravity. Each episode draws a target elbow angle; the agent
    must bring the forearm there and hold it. It never sees the joint angle: it feels the
    arm only through the primary (Ia) and secondary (II) afferents of one Mileusnic (2006)
    muscle spindle per muscle (human gains), computed by the package's spindle chain
    (``spindle.chain.ArmChain``) from the muscles' fibre lengths, with the fusimotor drive
    (gamma_s, gamma_d) of the seed paper's PI template.

    ## Action Space
    The action space is a `Box(0, 1, (2,), float32)`: the neural excitations of the two
    muscles (MuJoCo muscle ``ctrl``; activation follows with time constants 10 ms / 40 ms).

    | Num | Action                          | Control Min | Control Max | Name (in XML) | Actuator | Type (Unit)          |
    |-----|---------------------------------|-------------|-------------|---------------|----------|----------------------|
    | 0   | excitation of the brachialis    | 0           | 1           | BRA           | muscle   | excitation (unitless)|
    | 1   | excitation of the triceps medial| 0           | 1           | TRImed        | muscle   | excitation (unitless)|

    An action holding NaN/inf or non-real values (complex, bool, strings), of the wrong
    shape or outside the box raises ``ValueError`` naming it; with ``clip_actions=True`` finite out-of-box actions are clipped instead.

    ## Observation Space
    A `Box(low, high, (5,), float32)` in v0 (9 with ``include_fusimotor=True``), `(7,)` in v1
    (``include_ib=True``: 11 with the fusimotor drive); rates are divided by 100 pps
    (``RATE_SCALE_PPS``). The joint angle is *not* observed. v1's first five entries are
    v0's, bit for bit.

    | Num (v0) | Num (v1) | Observation                          | Min | Max   | Muscle | Type (Unit)           |
    |----------|----------|--------------------------------------|-----|-------|--------|-----------------------|
    | 0        | 0        | Ia (primary afferent) rate / 100     | 0   | Inf   | BRA    | firing rate (100 pps) |
    | 1        | 1        | Ia rate / 100                        | 0   | Inf   | TRImed | firing rate (100 pps) |
    | 2        | 2        | II (secondary afferent) rate / 100   | 0   | Inf   | BRA    | firing rate (100 pps) |
    | 3        | 3        | II rate / 100                        | 0   | Inf   | TRImed | firing rate (100 pps) |
    | 4        | 4        | target elbow flexion                 | 0   | 2.269 | -      | angle (rad)           |
    | -        | 5        | Ib (tendon organ afferent) rate / 100 | 0  | Inf   | BRA    | firing rate (100 pps) |
    | -        | 6        | Ib rate / 100                        | 0   | Inf   | TRImed | firing rate (100 pps) |
    | 5        | 7        | gamma static drive / 100 (optional)  | 0   | Inf   | BRA    | firing rate (100 pps) |
    | 6        | 8        | gamma static drive / 100 (optional)  | 0   | Inf   | TRImed | firing rate (100 pps) |
    | 7        | 9        | gamma dynamic drive / 100 (optional) | 0   | Inf   | BRA    | firing rate (100 pps) |
    | 8        | 10       | gamma dynamic drive / 100 (optional) | 0   | Inf   | TRImed | firing rate (100 pps) |

    Ib (v1) is the aggregate rate of each muscle's Golgi tendon organs (Lin & Crago 2002,
    ``spindle.tendon_organ``, human preset, ``docs/gto.md``) driven by the muscle's tendon
    force: its MuJoCo muscle force, active and passive (``-data.actuator_force`` of the BRA
    and TRImed actuators), read after every 2 ms physics step (``actuatorfrc`` sensors, the
    last from MuJoCo's ``mj_fwdActuation`` at the step's end state); the organs take one
    exact step per physics step, so they end each env step with the physics. The force
    scale is 4 N x F_max / 22 N (BRA 179.5 N, TRImed 113.5 N). A non-finite force (only in
    a diverged physics state) holds the previous force and one above 10^5 N is clamped, both
    counted (``env.unwrapped.tendon_organs.held`` / ``.clamped``): Ib is never NaN and never
    negative.

    The rates are the chain's output at the end of the env step. The observation never holds
    NaN: bad sensor samples are rejected by the chain (the previous output is kept), and a
    non-finite physics state raises ``RuntimeError`` instead of being observed.

    ``info`` carries the raw signals: ``angle_deg``, ``angular_velocity_deg_s``,
    ``target_deg``, ``angle_error_deg`` (angle - target), ``length_L0`` and ``velocity_L0_s``
    (the low-passed fibre lengths the spindles were stretched by, (2,)), ``gamma_static_pps``,
    ``gamma_dynamic_pps``, ``ia_pps``, ``ii_pps`` ((2,), BRA then TRImed, in pps),
    ``time_s`` (physics time), ``sensor_time_s`` (the chain's last sample time),
    ``sensor_samples`` (samples pushed in the step), ``reward_distance``, ``reward_control``;
    in v1 also ``force_N`` (the tendon forces at the step's end, (2,), N) and ``ib_pps``
    ((2,), pps).

    ## Rewards
    ***reward*** *=* *reward_distance + reward_control*, with
    *reward_distance* $= -w_{dist} |\theta - \theta_{target}|$ (rad, after the step) and
    *reward_control* $= -w_{ctrl} \|a\|_2^2$; $w_{dist}$ = ``distance_reward_weight``
    (default 1), $w_{ctrl}$ = ``control_cost_weight`` (default 0.05).

    ## Starting State
    Elbow flexion uniform over ``initial_angle_ranges_deg`` (default 10-120 deg), at rest,
    muscles inactive; the target uniform over the union of ``target_ranges_deg`` (default
    15-115 deg). ``reset(options={"target_deg": x, "angle_deg": y})`` fixes either. The
    spindle chain starts at equilibrium on the initial lengths.

    ## Timing
    Each step lasts ``dt = 1 / control_hz`` (default 20 ms): 10 MuJoCo steps of 2 ms, a
    sensor sample after each (500 Hz: the exact fibre lengths, or the angle for
    ``afferent_source="reduced"``), all pushed through the chain in one block call; the
    spindles advance in 1 ms sub-steps up to the end of the step.

    ## Episode End
    ### Termination
    Never terminates.
    ### Truncation
    200 steps (4 s at 50 Hz) when made with ``gymnasium.make``.

    ## Arguments
    ```python
    import gymnasium as gym
    import proprio_env  # registers the envs
    env = gym.make("proprio_env/ElbowReach-v0", afferent_source="reduced")
    ```

    | Parameter                  | Type        | Default           | Description |
    |----------------------------|-------------|-------------------|-------------|
    | `control_hz`               | float       | `50`              | env steps per second (0.1-500); 1/control_hz must be a multiple of the 2 ms physics step |
    | `afferent_source`          | str         | `"exact"`         | `"exact"` (MuJoCo fibre lengths), `"reduced"` (angle -> fitted lengths) or `"encoder"` (simulated AX-12 -> prosthesis chain) |
    | `backend`                  | str         | `"auto"`          | spindle chain backend: `"auto"` (C where a compiler or a valid cached library exists, numpy otherwise; `env.unwrapped.backend` says which was picked), `"numpy"` or `"c"` |
    | `chain_config`             | ChainConfig | `None`            | chain settings (its `backend` is replaced by `backend`; its `fits_path`, if set, must be fits of `xml_file`) |
    | `encoder_params`           | EncoderParams | `AX12`          | the simulated encoder (source `"encoder"`) |
    | `include_fusimotor`        | bool        | `False`           | append gamma_s, gamma_d to the observation |
    | `include_ib`               | bool        | v0 `False`, v1 `True` | observe Ib of both muscles (entries 5-6) |
    | `target_ranges_deg`        | pairs       | `((15, 115),)`    | intervals the target is drawn from (e.g. leave bands out for held-out evaluation) |
    | `initial_angle_ranges_deg` | pairs       | `((10, 120),)`    | intervals the initial angle is drawn from |
    | `distance_reward_weight`   | float       | `1`               | $w_{dist}$ (>= 0) |
    | `control_cost_weight`      | float       | `0.05`            | $w_{ctrl}$ (>= 0) |
    | `clip_actions`             | bool        | `False`           | clip out-of-box actions instead of raising |
    | `xml_file`                 | str or path | `None`            | another MJCF with the same names (default `models/elbow.xml`); its length fits are made on load (about 0.6 s, cached by the file's sha256) unless it is the bundled model |
    | `render_mode`              | str         | `None`            | `"rgb_array"` (headless with `MUJOCO_GL=egl`) |
    | `width`, `height`          | int         | `320`             | rendered image size (pixels, at most the model's offscreen buffer, 640 x 480) |

    Every argument is checked at construction and a bad one raises ``ValueError`` naming
    it: a float is any real number (numpy scalars included; not a bool, string or complex),
    an int any integer (not a bool), a bool only ``True``/``False`` (numpy's included).
    An edited model whose fibre lengths leave 0.5-1.5 L0 raises
    ``spindle.LengthFitsError`` naming the muscle, the angle and the length.

    ## Version History
    * v0: initial release (Mileusnic 2006 spindles with human gains, seed-paper fusimotor
      template, 50 Hz control, 500 Hz sensor). Later in v0: ``backend`` defaults to
      ``"auto"``; the physics steps through ``mujoco.rollout`` (the warm start zeroed at each
      env step, tendon lengths from sensors) so that ``gymnasium.make_vec`` (a native
      vector env) gives the same observations; the encoder draws its randomness in chunks of
      64 readings from two streams spawned from the env's generator, which changes the
      encoder's random numbers (and the target/angle draws after the first episode) for a
      given seed.
      Later in v0: the single and the vector env are one env core (n = 1 and n envs);
      ``reset`` refuses a seed that is not ``None`` or an integer >= 0 and checks every
      option before it changes anything (``ValueError``); the chain behind
      ``env.unwrapped.afferents.chain`` is the batched chain of one arm (counters (1,)).
    * v1: the observation gains Ib of BRA and TRImed (Golgi tendon organs from the muscles'
      MuJoCo force) at entries 5-6, the fusimotor drive (optional) moving to 7-10; ``info``
      gains ``force_N`` and ``ib_pps``. The same class with ``include_ib=True``; v0 is
      unchanged (Gymnasium warns that a newer version exists when v0 is made).
    """

    drive = MuscleDrive
