"""The MJCF elbow and the exact length model against OpenSim (tests/data/arm26_elbow_oracle.csv).

The oracle was written by OpenSim 4.6 from Arm26 (scripts/make_length_oracle.py); nothing in
it comes from this project's code.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from proprio_env.body.model import JOINT, MUSCLES, SERVO, load_model, model_path
from proprio_env.body.muscle_length import (
    MuscleGeometry,
    fibre_length_L0,
    fibre_state,
    fibre_velocity_L0_s,
    muscle_geometry,
    sweep,
)

ORACLE = Path(__file__).parent / "data" / "arm26_elbow_oracle.csv"


def read_oracle() -> dict[str, np.ndarray]:
    lines = [ln for ln in ORACLE.read_text().splitlines() if ln and not ln.startswith("#")]
    table = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    return {name: table[:, i] for i, name in enumerate(lines[0].split(","))}


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return load_model()


@pytest.fixture(scope="module")
def oracle() -> dict[str, np.ndarray]:
    return read_oracle()


@pytest.fixture(scope="module")
def exact(model, oracle):
    return sweep(model, oracle["elbow_flex_rad"])


def test_oracle_covers_0_to_130_deg(oracle):
    deg = oracle["elbow_flex_deg"]
    assert deg[0] == 0.0 and deg[-1] == 130.0 and np.all(np.diff(deg) == 1.0)


def test_model_file_is_packaged_and_credits_arm26():
    text = model_path().read_text()
    assert model_path().name == "elbow.xml"
    assert "Holzbaur" in text and "CC BY 3.0" in text


def test_names_range_and_actuators(model):
    assert model.joint(JOINT).type == mujoco.mjtJoint.mjJNT_HINGE
    np.testing.assert_allclose(model.joint(JOINT).range, [0.0, np.radians(130.0)], atol=1e-8)
    for name in MUSCLES:
        assert model.tendon(name).id >= 0
        act = model.actuator(name)
        assert act.dyntype == mujoco.mjtDyn.mjDYN_MUSCLE
        assert act.trntype == mujoco.mjtTrn.mjTRN_TENDON
    servo = model.actuator(SERVO)
    assert servo.trntype == mujoco.mjtTrn.mjTRN_JOINT
    np.testing.assert_allclose(servo.ctrlrange, [0.0, np.radians(130.0)], atol=1e-8)


def test_elbow_axis_and_arm26_body_parameters(model):
    # GEOMETRY_arm26_BRA_TRImed.md: r_elbow axis, r_ulna_radius_hand mass, COM and inertia.
    axis = np.array([0.04940001, 0.03660001, 0.99810825])
    np.testing.assert_allclose(model.jnt_axis[model.joint(JOINT).id], axis / np.linalg.norm(axis))
    forearm = model.body("r_ulna_radius_hand")
    np.testing.assert_allclose(forearm.mass, 1.534315)
    np.testing.assert_allclose(forearm.ipos, [0.0, -0.181479, 0.0])
    np.testing.assert_allclose(sorted(forearm.inertia), sorted([0.019281, 0.001571, 0.020062]))
    np.testing.assert_allclose(forearm.pos, [0.0061, -0.2904, -0.0123])


def test_gravity_points_along_opensim_minus_y(model):
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    rot = data.xmat[model.body("r_humerus").id].reshape(3, 3)
    np.testing.assert_allclose(rot.T @ model.opt.gravity, [0.0, -9.8066, 0.0], atol=1e-12)


@pytest.mark.parametrize(
    ("name", "force_N", "optimal_m", "slack_m", "pennation_rad"),
    [("BRA", 987.26, 0.0858, 0.0535, 0.0), ("TRImed", 624.3, 0.1138, 0.0908, 0.15707963)],
)
def test_muscle_parameters_are_arm26(model, name, force_N, optimal_m, slack_m, pennation_rad):
    geometry = muscle_geometry(model, name)
    assert geometry.optimal_fibre_length_m == pytest.approx(optimal_m, abs=1e-12)
    assert geometry.tendon_slack_length_m == pytest.approx(slack_m, abs=1e-12)
    assert geometry.pennation_at_optimal_rad == pytest.approx(pennation_rad, abs=1e-8)
    assert model.actuator_gainprm[model.actuator(name).id, 2] == pytest.approx(force_N)


@pytest.mark.parametrize("j", range(len(MUSCLES)))
def test_mtu_length_matches_opensim(exact, oracle, j):
    error_mm = (exact.mtu_length_m[:, j] - oracle[f"{MUSCLES[j]}_mtu_length_m"]) * 1e3
    assert np.sqrt(np.mean(error_mm**2)) <= 0.01
    assert np.max(np.abs(error_mm)) <= 0.05


@pytest.mark.parametrize("j", range(len(MUSCLES)))
def test_moment_arm_matches_opensim(exact, oracle, j):
    error_mm = (exact.moment_arm_m[:, j] - oracle[f"{MUSCLES[j]}_moment_arm_m"]) * 1e3
    assert np.max(np.abs(error_mm)) <= 0.5


@pytest.mark.parametrize("j", range(len(MUSCLES)))
def test_fibre_length_matches_opensim_passive_equilibrium(exact, oracle, j):
    error = exact.fibre_length_L0[:, j] - oracle[f"{MUSCLES[j]}_norm_fiber_length"]
    assert np.max(np.abs(error)) <= 0.005


@pytest.mark.parametrize("j", range(len(MUSCLES)))
def test_fibre_length_matches_opensim_rigid_tendon(exact, oracle, j):
    # Same physics (rigid tendon, constant-width pennation): only the path length differs.
    error = exact.fibre_length_L0[:, j] - oracle[f"{MUSCLES[j]}_rigid_norm_fiber_length"]
    assert np.max(np.abs(error)) <= 0.001


def test_pennation_matches_opensim(exact, oracle):
    j = MUSCLES.index("TRImed")
    np.testing.assert_allclose(exact.pennation_rad[:, j], oracle["TRImed_pennation_rad"], atol=2e-3)
    np.testing.assert_array_equal(exact.pennation_rad[:, MUSCLES.index("BRA")], 0.0)


def test_mujoco_own_normalisation_misses_pennation(model, exact, oracle):
    # Why the exact model exists: MuJoCo's (l - l_ts) / L0 is the fibre length along the
    # tendon, which for TRImed is short of OpenSim's fibre length by more than 0.01 L0.
    j = MUSCLES.index("TRImed")
    geometry = muscle_geometry(model, "TRImed")
    along_L0 = (
        exact.mtu_length_m[:, j] - geometry.tendon_slack_length_m
    ) / geometry.optimal_fibre_length_m
    assert np.max(np.abs(along_L0 - oracle["TRImed_rigid_norm_fiber_length"])) > 0.01


def test_wrap_engages_where_opensim_wraps(model, oracle):
    data = mujoco.MjData(model)
    for k, q in enumerate(oracle["elbow_flex_rad"]):
        data.qpos[model.joint(JOINT).qposadr[0]] = q
        mujoco.mj_fwdPosition(model, data)
        for name in MUSCLES:
            tendon = model.tendon(name).id
            adr, num = data.ten_wrapadr[tendon], data.ten_wrapnum[tendon]
            on_geom = np.any(data.wrap_obj.reshape(-1)[adr : adr + num] >= 0)
            assert on_geom == bool(oracle[f"{name}_wrap_engaged"][k]), (name, k)


@pytest.mark.parametrize("j", range(len(MUSCLES)))
def test_fibre_velocity_matches_opensim_slope(model, exact, oracle, j):
    # dL/dt at 1 rad/s equals dL/dangle; compare with OpenSim's rigid-tendon curve's central
    # difference (1 deg steps, O(h^2) error well below the tolerance away from wrap onsets).
    name = MUSCLES[j]
    omega_rad_s = 1.0
    velocity = fibre_velocity_L0_s(
        exact.mtu_length_m[:, j],
        -exact.moment_arm_m[:, j] * omega_rad_s,
        muscle_geometry(model, name),
    )
    slope = np.gradient(oracle[f"{name}_rigid_norm_fiber_length"], oracle["elbow_flex_rad"])
    np.testing.assert_allclose(velocity[1:-1], slope[1:-1], atol=0.002)


def test_fibre_state_reads_a_running_simulation(model, oracle):
    data = mujoco.MjData(model)
    k = 100
    data.qpos[0] = oracle["elbow_flex_rad"][k]
    data.qvel[0] = -2.0  # extending at 2 rad/s
    mujoco.mj_forward(model, data)
    length_L0, velocity_L0_s = fibre_state(model, data)
    for j, name in enumerate(MUSCLES):
        assert length_L0[j] == pytest.approx(oracle[f"{name}_rigid_norm_fiber_length"][k], abs=1e-3)
    slope = [
        np.gradient(oracle[f"{m}_rigid_norm_fiber_length"], oracle["elbow_flex_rad"])[k]
        for m in MUSCLES
    ]
    np.testing.assert_allclose(velocity_L0_s, -2.0 * np.array(slope), atol=0.004)
    assert velocity_L0_s[MUSCLES.index("BRA")] > 0  # extension lengthens the flexor


def test_fibre_length_and_velocity_formulas():
    geometry = MuscleGeometry("M", 0.1, 0.05, np.radians(30.0))
    # At L0 the fibre is at its optimal pennation: along-tendon length L0 cos(alpha0).
    mtu = 0.05 + 0.1 * np.cos(np.radians(30.0))
    assert fibre_length_L0(mtu, geometry) == pytest.approx(1.0)
    assert fibre_velocity_L0_s(mtu, 0.02, geometry) == pytest.approx(
        0.02 * np.cos(np.radians(30.0)) / 0.1
    )
    np.testing.assert_allclose(fibre_length_L0(np.array([[mtu], [mtu]]), geometry), [[1.0], [1.0]])


@pytest.mark.parametrize("bad", [np.nan, -0.01, np.radians(130.0) + 1e-6, np.inf])
def test_bad_angles_are_refused(model, bad):
    with pytest.raises(ValueError, match="elbow angle"):
        sweep(model, np.array([0.5, bad]))


def test_bad_mtu_lengths_are_refused(model):
    geometry = muscle_geometry(model, "TRImed")
    with pytest.raises(ValueError, match="finite"):
        fibre_length_L0(np.nan, geometry)
    with pytest.raises(ValueError, match="slack"):
        fibre_length_L0(0.05, geometry)
    with pytest.raises(ValueError, match="finite"):
        fibre_velocity_L0_s(0.17, np.nan, geometry)


def test_servo_holds_target_against_gravity(model):
    model = load_model()  # a private copy: opt is changed below
    model.opt.disableactuator = 1 << 1  # muscles off: servo-driven prosthesis mode
    data = mujoco.MjData(model)
    data.ctrl[model.actuator(SERVO).id] = np.radians(90.0)
    for _ in range(1500):
        mujoco.mj_step(model, data)
    assert abs(np.degrees(data.qpos[0]) - 90.0) < 3.0
    assert abs(data.qvel[0]) < 1e-3


def test_forearm_falls_to_full_extension_under_gravity():
    model = load_model()
    model.opt.disableactuator = (1 << 1) | (1 << 2)
    data = mujoco.MjData(model)
    data.qpos[0] = 1.0
    for _ in range(1500):
        mujoco.mj_step(model, data)
    assert abs(data.qpos[0]) < np.radians(0.5)
