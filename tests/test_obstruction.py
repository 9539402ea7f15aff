"""The optional obstacle and the obstructed-movement experiment (seed paper Fig. 7)."""

import numpy as np
import pytest

from proprio_env.body.model import load_model
from proprio_env.body.servo_motion import drive_servo
from proprio_env.experiments.obstruction import ObstructionSetup, run_experiment

pytest.importorskip("mujoco")


@pytest.mark.parametrize("obstacle_deg", [40.0, 70.0, 100.0])
def test_the_obstacle_stops_the_forearm_where_asked(obstacle_deg):
    model = load_model(obstacle_deg=obstacle_deg)
    t = np.arange(0, 1.5, model.opt.timestep)
    motion = drive_servo(np.clip(20 + 130 * t, 20, 125), model)
    # soft contact: the forearm sinks in by a fraction of a degree, never more than 1 deg
    assert motion.angle_deg.max() <= obstacle_deg + 1.0
    assert motion.angle_deg[-1] == pytest.approx(obstacle_deg, abs=0.3)
    free = drive_servo(np.clip(20 + 130 * t, 20, 125), load_model())
    assert free.angle_deg.max() > 120


def test_obstacle_outside_the_joint_range_is_refused():
    with pytest.raises(ValueError, match="obstacle_deg=140"):
        load_model(obstacle_deg=140)


def test_only_the_intended_template_signals_the_unexpected_stop():
    result = run_experiment(ObstructionSetup(duration_s=1.4))
    m = result.metrics
    assert m["overshoot_deg"] < 1.0
    measured = m["held measured/voluntary stop/BRA_ii_rms_pps"]
    intended = m["held intended/voluntary stop/BRA_ii_rms_pps"]
    # measured ~0.1 pps (the chain cannot tell the stops apart), intended ~15 pps
    assert measured < 1.0
    assert intended > 5.0 and intended > 10 * measured
