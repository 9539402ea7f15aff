"""Joint torque -> tendon forces (spindle.chain.force) against OpenSim's moment arms, and the
servo's load reading: simulated words (proprio_env.body.encoder) and their decoding
(spindle.chain.sensor)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from proprio_env.body.encoder import LoadSensor, load_readings
from spindle.chain.force import load_moment_arm_fits, tendon_forces_N
from spindle.chain.sensor import (
    AX12_LOAD,
    INVALID_READING,
    LOAD_MAX_WORD,
    LoadParams,
    load_torque_Nm,
    valid_load_words,
)

ORACLE = Path(__file__).parent / "data" / "arm26_elbow_oracle.csv"
SHARED_CSV = (Path(__file__).resolve().parents[2] / "shared" / "reference" / "opensim"
              / "arm26_elbow_BRA_TRImed.csv")


@pytest.fixture(scope="module")
def fits():
    from proprio_env.body.model import model_path

    return load_moment_arm_fits(model=model_path())  # refuses a table of another model


@pytest.fixture(scope="module")
def oracle():
    lines = [ln for ln in ORACLE.read_text().splitlines() if ln and not ln.startswith("#")]
    return np.genfromtxt(lines, delimiter=",", names=True)


def test_moment_arms_match_opensim(fits, oracle):
    """Against OpenSim's moment arms (tests/data, = the shared CSV) over 0-130 deg: measured
    max |error| 0.21 mm = 1.4 % BRA (at full extension, where the BRA path wraps and MuJoCo's
    wrap departs from OpenSim's; 0 beyond 50 deg), 0.023 mm = 0.12 % TRImed."""
    angle = oracle["elbow_flex_rad"]
    arms = fits.moment_arms_m(angle, clip=True)
    for j, muscle in enumerate(fits.muscles):
        ref = oracle[f"{muscle}_moment_arm_m"]
        err = np.abs(arms[:, j] - ref)
        assert err.max() < 2.5e-4, muscle
        assert np.max(err / np.abs(ref)) < 0.016, muscle
        assert np.max(err[50:] / np.abs(ref[50:])) < 0.0015, muscle


def test_table_interpolates_mujoco_between_its_angles(fits):
    from proprio_env.body.moment_arm_fitting import moment_arms_exact_m

    angle = np.random.default_rng(3).uniform(*fits.valid_range_rad, 200)
    np.testing.assert_allclose(fits.moment_arms_m(angle), moment_arms_exact_m(angle),
                               atol=2e-5)  # measured 1.6e-5 m (TRImed, the wrap's kink)


def test_oracle_moment_arms_are_the_shared_csv(oracle):
    if not SHARED_CSV.exists():
        pytest.skip(f"{SHARED_CSV} not present")
    shared = np.genfromtxt(SHARED_CSV, delimiter=",", names=True)
    for muscle in ("BRA", "TRImed"):
        np.testing.assert_allclose(oracle[f"{muscle}_moment_arm_m"],
                                   shared[f"{muscle}_moment_arm_m"], rtol=1e-7, atol=1e-9)


def test_split_carries_the_torque_and_is_never_negative(fits):
    rng = np.random.default_rng(0)
    angle = rng.uniform(*fits.valid_range_rad, 500)
    tau = rng.normal(0, 5, 500)
    tau[:10] = 0.0
    forces = tendon_forces_N(tau, angle, fits)
    arms = fits.moment_arms_m(angle)
    assert forces.shape == (500, 2) and np.all(forces >= 0)
    np.testing.assert_allclose(np.sum(forces * arms, axis=-1), tau, rtol=1e-12, atol=1e-12)
    assert np.all(forces[tau > 0, 1] == 0) and np.all(forces[tau < 0, 0] == 0)
    assert np.all(forces[:10] == 0)
    # 1 N m of flexion at 90 deg: BRA's force is 1 / its moment arm (~ 50 N)
    f = tendon_forces_N(1.0, np.pi / 2, fits)
    assert f[0] == pytest.approx(1.0 / fits.moment_arms_m(np.pi / 2)[0])


def test_split_refuses_bad_inputs(fits):
    with pytest.raises(ValueError, match="torque_Nm"):
        tendon_forces_N(np.nan, 1.0, fits)
    with pytest.raises(ValueError, match="outside"):
        tendon_forces_N(1.0, 3.0, fits)  # outside the table's range
    assert tendon_forces_N(1.0, 3.0, fits, clip=True).shape == (2,)


# -- the load reading ------------------------------------------------------------------------
def test_load_words_round_trip_within_half_a_count():
    ideal = LoadParams(noise_counts=0.0, invalid_rate=0.0)
    tau = np.linspace(-1.6, 1.6, 1001)  # past the maximum torque both ways: saturates
    words = LoadSensor(ideal, rng=0).read_block(tau)
    assert np.all(valid_load_words(words))
    back = load_torque_Nm(words, ideal)
    inside = np.abs(tau) <= ideal.max_torque_Nm
    assert np.max(np.abs(back - tau)[inside]) <= 0.5 * ideal.Nm_per_count + 1e-12
    np.testing.assert_allclose(back[~inside], np.sign(tau[~inside]) * 1.5)
    assert words[tau < -0.01].min() >= 1024  # CW: bit 10 set (flexion is CCW, sign +1)
    flipped = LoadSensor(ideal, sign=-1, rng=0).read_block(tau)
    np.testing.assert_allclose(load_torque_Nm(flipped, ideal, sign=-1), back)


def test_load_noise_and_invalid_readings_at_their_rates():
    params = LoadParams(noise_counts=3.0, invalid_rate=0.05)
    words = LoadSensor(params, rng=1).read_block(np.full(40000, 0.6))
    ok = valid_load_words(words)
    # invalid: all dropouts and the corrupted words above 2047 (2047/65536 of them are not)
    assert (~ok).mean() == pytest.approx(0.05 * (1 - 0.5 * 2048 / 65536), abs=0.004)
    assert np.count_nonzero(words == INVALID_READING) == pytest.approx(0.025 * 40000, rel=0.1)
    counts = load_torque_Nm(words[ok], params) / params.Nm_per_count
    clean = counts[np.abs(counts - 0.6 / params.Nm_per_count) < 30]  # drop the spikes
    assert clean.std() == pytest.approx(np.sqrt(3.0**2 + 1 / 12), rel=0.05)


def test_load_decoder_refuses_invalid_words():
    assert list(valid_load_words(np.array([0, 1023, 1024, 2047, 2048, -1, 3.5, np.nan]))) == [
        True, True, True, True, False, False, False, False]
    with pytest.raises(ValueError, match="2048"):
        load_torque_Nm(np.array([5, 2048]))
    assert LOAD_MAX_WORD == 2047
    draws = np.zeros((4, 3))
    draws[1] = 1.0  # never invalid
    np.testing.assert_array_equal(load_readings(np.array([0.0, 1.5, -1.5]), draws, AX12_LOAD),
                                  [0, 1023, 2047])


def test_moment_arm_file_errors_name_the_remedy(tmp_path):
    bad = tmp_path / "m.json"
    bad.write_text("{}")
    with pytest.raises(ValueError, match="fit_moment_arms"):
        load_moment_arm_fits(bad)
    other = tmp_path / "other.xml"
    other.write_text("<mujoco/>")
    with pytest.raises(ValueError, match="another model"):
        load_moment_arm_fits(model=other)
