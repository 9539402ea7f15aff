"""Which MuJoCo models the spindle wrapper takes, and what it says about the others."""
from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest

from proprio_env.wrappers import SpindleAfferents
from proprio_env.wrappers.muscles import find_muscles

pytest.importorskip("imageio", reason="gymnasium.envs.mujoco needs imageio")

# one tendon from a world site to a swinging body, driven by a <general> actuator with
# MuJoCo's muscle gain, beside a plain motor on the joint
_GENERAL_MUSCLE_XML = """
<mujoco>
  <worldbody>
    <site name="origin" pos="0 0 0"/>
    <body pos="0 0 -0.3">
      <joint name="swing" type="hinge" axis="0 1 0" range="-60 60" limited="true"/>
      <geom size="0.05" mass="1"/>
      <site name="insertion" pos="0.1 0 0"/>
    </body>
  </worldbody>
  <tendon><spatial name="line"><site site="origin"/><site site="insertion"/></spatial></tendon>
  <actuator>
    <general name="muscle" tendon="line" dyntype="muscle" gaintype="muscle" biastype="muscle"
             gainprm="0.75 1.05 100 200 0.5 1.6 1.5 1.3 1.2"
             biasprm="0.75 1.05 100 200 0.5 1.6 1.5 1.3 1.2"/>
    <motor name="motor" joint="swing"/>
  </actuator>
</mujoco>
"""


def test_a_general_actuator_with_muscle_gain_is_a_muscle_and_the_motor_is_skipped():
    model = mujoco.MjModel.from_xml_string(_GENERAL_MUSCLE_XML)
    muscles = find_muscles(model)
    assert muscles.names == ("muscle",)
    # closed form: the tendon's length between the sites over the joint range, the 2-D
    # distance from the origin to a point 0.1 m off a 0.3 m pendulum
    angle = np.deg2rad(np.linspace(-60.0, 60.0, 20001))
    length_m = np.hypot(0.1 * np.cos(angle), -0.3 + 0.1 * np.sin(angle))
    # MuJoCo finds lengthrange by simulation: measured within 4e-5 m of the sweep
    np.testing.assert_allclose(model.actuator_lengthrange[0], [length_m.min(), length_m.max()],
                               atol=1e-4)
    np.testing.assert_allclose(muscles.optimal_length_m,
                               np.diff(model.actuator_lengthrange[0]) / (1.05 - 0.75))


@pytest.mark.parametrize("env_id", ["Ant-v5", "Humanoid-v5"])
def test_gymnasium_motor_models_are_refused_with_what_works(env_id):
    env = gym.make(env_id)
    try:
        with pytest.raises(ValueError) as err:
            SpindleAfferents(env)
        text = str(err.value)
        assert f"none of its {env.unwrapped.model.nu} actuators" in text
        assert "<muscle>" in text and "Humanoid-v5" in text and "docs/wrapper.md" in text
        assert "name the actuators" not in text     # the old hint led to a second error
        name = mujoco.mj_id2name(env.unwrapped.model, mujoco.mjtObj.mjOBJ_ACTUATOR, 0)
        if name:
            with pytest.raises(ValueError, match="only muscle actuators"):
                SpindleAfferents(env, muscles=[name])
    finally:
        env.close()
