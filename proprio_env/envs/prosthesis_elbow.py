# ruff: noqa: E501  (Gymnasium-style markdown tables in the class docstring)
"""``proprio_env/ProsthesisElbow-v0`` / ``-v1``: a servo-driven prosthetic elbow with artificial
proprioception through its encoder, as in the seed paper (and, in v1, the force sense)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces

from proprio_env.body.model import SERVO
from proprio_env.body.moment_arm_fitting import fit_moment_arm_document
from proprio_env.envs.base import ElbowProprioEnv
from proprio_env.envs.core import MUSCLE_GROUP_BIT, Drive
from spindle.chain.force import MomentArmFits, load_moment_arm_fits, tendon_forces_N


class ServoDrive(Drive):
    """The position servo's command, normalised over the joint range (``Box(-1, 1, (1,))``),
    the muscles disabled (passive)."""

    disabled_groups: ClassVar[int] = MUSCLE_GROUP_BIT
    default_source: ClassVar[str] = "encoder"
    default_control_cost_weight: ClassVar[float] = 0.0

    def __init__(self, model: Any, joint_range_deg: tuple[float, float]) -> None:
        super().__init__(model, joint_range_deg)
        self._servo_id = model.actuator(SERVO).id
        lo, hi = joint_range_deg
        self._command_mid_deg = 0.5 * (lo + hi)
        self._command_half_deg = 0.5 * (hi - lo)

    def action_space(self) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (1,), dtype=np.float32)

    def commands_deg(self, actions: np.ndarray) -> np.ndarray:
        """The servo commands (deg) of (valid) actions (n, 1)."""
        return self._command_mid_deg + self._command_half_deg * actions[:, 0]

    def write_controls(self, ctrl: np.ndarray, actions: np.ndarray) -> None:
        ctrl[:, self._servo_id] = np.radians(self.commands_deg(actions))

    def rest_controls(self, ctrl: np.ndarray, angle_deg: float) -> None:
        super().rest_controls(ctrl, angle_deg)
        ctrl[self._servo_id] = np.radians(angle_deg)

    def info(self, ctrl: np.ndarray, degrees: Any = np.degrees) -> dict[str, Any]:
        return {"command_deg": degrees(ctrl[..., self._servo_id])}

    def prepare_forces(self, model_file: Path) -> None:
        """The moment-arm table of the model: the bundled ``models/moment_arm_fits.json``
        if it was made from ``model_file``, else tabulated from it now (MuJoCo's tendon
        Jacobian every 0.5 deg, as ``scripts/fit_moment_arms.py`` does)."""
        try:
            self._arms = load_moment_arm_fits(model=model_file)
        except ValueError:
            doc = fit_moment_arm_document(model_file)
            names = tuple(doc["muscles"])
            self._arms = MomentArmFits(
                muscles=names, table_m=tuple(tuple(doc["fits"][m]["table_m"]) for m in names),
                valid_range_rad=tuple(doc["valid_range_rad"]),
                model_sha256=doc["model_sha256"],
                max_error_m=tuple(doc["fits"][m]["max_error_m"] for m in names))
        self._gear = float(self.model.actuator_gear[self._servo_id, 0])

    def tendon_forces_N(self, actuator_force: np.ndarray, angle_rad: np.ndarray
                        ) -> np.ndarray:
        """The servo's joint torque split into BRA and TRImed tendon forces by the elbow's
        moment arms (:func:`spindle.chain.force.tendon_forces_N`: flexion torque on BRA,
        extension torque on TRImed, none on the other): the muscles are disabled and carry
        no force, the servo carries the load, as the prosthesis chain reads it from the
        servo's load reading. A non-finite torque or angle gives NaN forces (the force
        sense's hold rule)."""
        torque = self._gear * np.asarray(actuator_force)[..., self._servo_id]
        angle = np.asarray(angle_rad, dtype=np.float64)
        bad = ~(np.isfinite(torque) & np.isfinite(angle))
        if bad.any():
            torque, angle = np.where(bad, 0.0, torque), np.where(bad, 0.0, angle)
        forces = tendon_forces_N(torque, angle, self._arms, clip=True)
        if bad.any():
            forces[bad] = np.nan
        return forces


class ProsthesisElbowEnv(ElbowProprioEnv):
    r"""
    ## Description
    The Arm26 elbow (``models/elbow.xml``) as a prosthesis: its muscles are passive
    (disabled) and a position servo (``r_elbow_servo``: kp 100 N m/rad, kv 5 N m s/rad, torque
    limit 20 N m) moves the forearm under gravity. As in the seed paper, the servo's own
    position encoder (a simulated Dynamixel AX-12: ~500 Hz jittered readings, 0.29 deg
    counts, noise, rare invalid readings) feeds the prosthesis chain: median filter (7), f(x),
    fitted BRA/TRImed fibre lengths, 20 Hz tracking low-pass, PI fusimotor template and the
    Mileusnic (2006) spindles with human gains. The agent commands the servo and must bring
    the elbow to a target angle drawn each episode and hold it, feeling the arm only through
    the Ia and II afferents it produces.

    ## Action Space
    The action space is a `Box(-1, 1, (1,), float32)`: the servo's commanded angle,
    normalised over the joint range, $\theta_{cmd} = 65° + 65° \cdot a$.

    | Num | Action                          | Control Min | Control Max | Name (in XML)  | Actuator | Type (Unit)              |
    |-----|---------------------------------|-------------|-------------|----------------|----------|--------------------------|
    | 0   | commanded elbow flexion         | -1          | 1           | r_elbow_servo  | position | angle (65 deg per unit, 0 at 65 deg) |

    An action holding NaN/inf or non-real values (complex, bool, strings), of the wrong
    shape or outside the box raises ``ValueError`` naming it; with ``clip_actions=True`` finite out-of-box actions are clipped instead.

    ## Observation Space
    A `Box(low, high, (5,), float32)` in v0 (9 with ``include_fusimotor=True``), `(7,)` in v1
    (``include_ib=True``; 11 with the fusimotor drive); rates are divided by 100 pps. The
    joint angle and the encoder readings are *not* observed.

    | Num (v0) | Num (v1) | Observation (BRA, then TRImed)                   | Min | Max   | Type (Unit)           |
    |----------|----------|--------------------------------------------------|-----|-------|-----------------------|
    | 0-1      | 0-1      | Ia (primary spindle afferent) rates / 100        | 0   | Inf   | firing rate (100 pps) |
    | 2-3      | 2-3      | II (secondary spindle afferent) rates / 100      | 0   | Inf   | firing rate (100 pps) |
    | 4        | 4        | target elbow flexion                             | 0   | 2.269 | angle (rad)           |
    | -        | 5-6      | Ib (tendon organ afferent) rates / 100           | 0   | Inf   | firing rate (100 pps) |
    | 5-8      | 7-10     | gamma static, gamma dynamic / 100 (optional)     | 0   | Inf   | firing rate (100 pps) |

    Ib (v1): the muscles are disabled and carry no force, so the tendon forces are the load
    the servo carries, as the prosthesis chain gets it from the servo's load reading: the
    servo's joint torque (``data.actuator_force`` of ``r_elbow_servo``, flexion positive)
    split by the elbow's moment arms (``spindle.chain.force.tendon_forces_N``: a flexion
    torque on BRA, an extension torque on TRImed, none on the other; the moment arms from
    ``models/moment_arm_fits.json``, or tabulated from an edited ``xml_file`` on load), read
    after every 2 ms physics step and fed to the tendon organs (Lin & Crago 2002, human
    preset), one exact step per physics step. The same rules as ElbowReach-v1: a non-finite
    torque or angle holds the previous force, a force above 10^5 N is clamped, both counted.

    The observation never holds NaN: invalid encoder readings are rejected by the chain
    (counted in ``env.unwrapped.afferents.chain.counters``), the previous output is kept.
    ``info`` carries the same raw signals as ElbowReach-v0 (``angle_deg``, ``target_deg``,
    ``angle_error_deg``, ``length_L0``, ``gamma_static_pps``, ``gamma_dynamic_pps``,
    ``ia_pps``, ``ii_pps``, ``sensor_samples`` ...) plus ``command_deg``; in v1 also
    ``force_N`` and ``ib_pps`` ((2,), N and pps).

    ## Rewards
    ***reward*** *=* $-w_{dist} |\theta - \theta_{target}|$ (rad, after the step)
    $- w_{ctrl} a^2$, with ``distance_reward_weight`` (default 1) and ``control_cost_weight``
    (default 0).

    ## Starting State
    Elbow flexion uniform over ``initial_angle_ranges_deg`` (default 10-120 deg), at rest,
    the servo holding that angle; target uniform over ``target_ranges_deg`` (default 15-115
    deg); ``reset(options={"target_deg": x, "angle_deg": y})`` fixes either. The encoder's
    noise, jitter and glitches come from the env's seeded generator.

    ## Timing
    Each step lasts ``dt = 1 / control_hz`` (default 20 ms): 10 MuJoCo steps of 2 ms; the
    encoder reads at its own jittered ~500 Hz times inside that interval (the angle
    interpolated between physics steps), and all the readings are pushed through the chain in
    one block call.

    ## Episode End
    ### Termination
    Never terminates.
    ### Truncation
    200 steps (4 s at 50 Hz) when made with ``gymnasium.make``.

    ## Arguments
    The same as ElbowReach-v0 (``control_hz``, ``afferent_source``, ``backend``,
    ``chain_config``, ``encoder_params``, ``include_fusimotor``, ``target_ranges_deg``,
    ``initial_angle_ranges_deg``, ``distance_reward_weight``, ``control_cost_weight``,
    ``clip_actions``, ``xml_file``, ``render_mode``, ``width``, ``height``, checked the same
    way; an edited ``xml_file`` gets its own length fits) with these defaults:

    | Parameter              | Type  | Default     | Description |
    |------------------------|-------|-------------|-------------|
    | `backend`              | str   | `"auto"`    | spindle chain backend: `"auto"` (C where a compiler or a valid cached library exists, numpy otherwise; `env.unwrapped.backend` says which), `"numpy"` or `"c"` |
    | `afferent_source`      | str   | `"encoder"` | `"encoder"` (the prosthesis chain), `"reduced"` (clean angle -> fitted lengths) or `"exact"` (MuJoCo fibre lengths of the passive muscles) |
    | `control_cost_weight`  | float | `0`         | $w_{ctrl}$ |
    | `include_ib`           | bool  | v0 `False`, v1 `True` | observe Ib of both muscles (entries 5-6) |

    ## Version History
    * v0: initial release (AX-12 encoder chain of the seed paper, human spindle gains, 50 Hz
      control). Later in v0: ``backend`` defaults to ``"auto"``; physics through
      ``mujoco.rollout`` (shared with the native vector env of ``gymnasium.make_vec``); the
      encoder draws its jitter, noise and glitches in chunks of 64 readings from two streams
      spawned from the env's generator: the random numbers for a given seed changed.
      Later in v0: the single and the vector env are one env core (n = 1 and n envs);
      ``reset`` refuses a seed that is not ``None`` or an integer >= 0 and checks every
      option before it changes anything (``ValueError``); the chain behind
      ``env.unwrapped.afferents.chain`` is the batched chain of one arm (counters (1,)).
    * v1: the observation gains Ib of BRA and TRImed from the servo's torque split by the
      moment arms (entries 5-6, the fusimotor drive moving to 7-10); ``info`` gains
      ``force_N`` and ``ib_pps``. v0 is unchanged.
    """

    drive = ServoDrive

    def command_deg(self, action: np.ndarray) -> float:
        """The servo command (deg) of a (valid) action."""
        return float(self.core.drive.commands_deg(np.asarray(action, dtype=float)[None, :])[0])
