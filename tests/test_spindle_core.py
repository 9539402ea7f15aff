"""Behaviour of the spindle model and its theta-method core.

The expected behaviour comes from the model's definition (Mileusnic et al. 2006) and the
seed paper, not from recorded outputs: closed-form equilibria, the preset relation, monotone
responses, batching, and refusal of bad input.
"""

import dataclasses

import numpy as np
import pytest

import spindle
from spindle import core

METHODS = sorted(spindle.METHODS)


def ramp(speed_L0_s=0.66, dt=1e-3, start=0.95, end=1.08, t_ramp=0.3, duration=1.0):
    t = np.arange(0, duration + dt / 2, dt)
    return np.clip(start + speed_L0_s * (t - t_ramp), start, end)


def test_equilibrium_tension_balances_the_fibre_forces():
    state = spindle.equilibrium_state(np.array([0.8, 1.0, 1.2]), 50.0, 80.0)
    c = core.columns(spindle.CAT)
    T = state.tension_FU.T
    f = state.activation.T
    force = core._force(T, state.velocity_root.T, state.length_L0,
                        c.beta0 + c.beta_drive * f, c.Gamma_drive * f, c)
    np.testing.assert_allclose(force, 0.0, atol=1e-15)
    # activation g^2 / (g^2 + freq^2): bag1 50 pps / 60, bag2 80 / 60, chain 80 / 90
    np.testing.assert_allclose(f[:, 0], [2500 / 6100, 6400 / 10000, 6400 / 14500])


@pytest.mark.parametrize(("method", "step_s", "atol_pps"), [
    ("trapezoidal", 1e-3, 1e-9),
    ("backward_euler", 1e-3, 1e-9),
    # Forward Euler cannot hold v = 0: rounding seeds the chatter of the infinitely stiff
    # |v|^0.3 damper, whose amplitude grows with the step (about 1.7 pps at 0.5 ms).
    ("forward_euler", 20e-6, 0.05),
])
def test_a_spindle_at_rest_stays_at_rest(method, step_s, atol_pps):
    state = spindle.equilibrium_state(1.0, 30.0, 40.0)
    ia0, ii0 = spindle.afferents(state)
    for _ in range(round(0.05 / step_s)):
        ia, ii = spindle.step(state, 1.0, 30.0, 40.0, step_s, method=method)
    np.testing.assert_allclose(ia, ia0, atol=atol_pps)
    np.testing.assert_allclose(ii, ii0, atol=atol_pps)


def test_human_preset_is_cat_divided_by_five():
    L = ramp(1.55)
    for gd, gs in [(0.0, 0.0), (70.0, 0.0), (0.0, 70.0)]:
        cat = spindle.simulate(L, 1e-3, gamma_dyn=gd, gamma_stat=gs, params=spindle.CAT)
        human = spindle.simulate(L, 1e-3, gamma_dyn=gd, gamma_stat=gs, params=spindle.HUMAN)
        np.testing.assert_allclose(human.ia, cat.ia / 5, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(human.ii, cat.ii / 5, rtol=1e-12, atol=1e-12)
    assert spindle.HUMAN.bag1.G_primary_pps_L0 == pytest.approx(4000.0, rel=1e-15)
    assert spindle.HUMAN.chain.G_secondary_pps_L0 == pytest.approx(1450.0, rel=1e-15)


def test_steady_state_rates_rise_monotonically_with_length():
    lengths = np.linspace(0.8, 1.3, 26)
    for gd, gs in [(0.0, 0.0), (70.0, 0.0), (0.0, 70.0)]:
        ia, ii = spindle.afferents(spindle.equilibrium_state(lengths, gd, gs))
        assert np.all(np.diff(ia) >= 0) and ia[-1] - ia[0] > 20
        assert np.all(np.diff(ii) >= 0) and ii[-1] - ii[0] > 20


def test_dynamic_drive_raises_the_velocity_response():
    L = ramp(1.55)
    hold = slice(-50, None)
    ramp_end = round((0.3 + 0.13 / 1.55) / 1e-3)
    passive = spindle.simulate(L, 1e-3)
    dynamic = spindle.simulate(L, 1e-3, gamma_dyn=70.0)
    # dynamic sensitivity: the peak at the end of the ramp over the later hold level
    gain_passive = passive.ia[ramp_end] - passive.ia[hold].mean()
    gain_dynamic = dynamic.ia[ramp_end] - dynamic.ia[hold].mean()
    assert gain_dynamic > 1.5 * gain_passive > 0


def test_static_drive_raises_the_background_rate():
    ia0, ii0 = spindle.afferents(spindle.equilibrium_state(0.95))
    ia_s, ii_s = spindle.afferents(spindle.equilibrium_state(0.95, 0.0, 70.0))
    assert ia_s[0] > ia0[0] + 10
    assert ii_s[0] > ii0[0] + 5


def test_secondary_follows_length_with_little_velocity_sensitivity():
    L = ramp(1.55)
    r = spindle.simulate(L, 1e-3)
    ramp_end = round((0.3 + 0.13 / 1.55) / 1e-3)
    overshoot_ii = r.ii[ramp_end] - r.ii[-1]
    overshoot_ia = r.ia[ramp_end] - r.ia[-1]
    assert overshoot_ii < 0.5 * overshoot_ia


@pytest.mark.parametrize("method", METHODS)
def test_stepping_n_spindles_together_equals_each_alone(method):
    rng = np.random.default_rng(3)
    n = 5
    t = np.arange(0, 0.4, 1e-3)
    L = 1.0 + 0.05 * np.sin(2 * np.pi * rng.uniform(0.5, 3, n) * t[:, None]
                            + rng.uniform(0, 6, n))
    gd = rng.uniform(0, 120, n)
    gs = rng.uniform(0, 120, n)
    together = spindle.simulate(L, 1e-3, gamma_dyn=gd, gamma_stat=gs, method=method,
                                step=1e-4 if method == "forward_euler" else None)
    for k in range(n):
        alone = spindle.simulate(L[:, k], 1e-3, gamma_dyn=gd[k], gamma_stat=gs[k],
                                 method=method,
                                 step=1e-4 if method == "forward_euler" else None)
        np.testing.assert_allclose(together.ia[:, k], alone.ia, rtol=0, atol=1e-9)
        np.testing.assert_allclose(together.ii[:, k], alone.ii, rtol=0, atol=1e-9)


def test_state_arrays_have_a_leading_spindle_axis():
    state = spindle.equilibrium_state(np.full(7, 1.0))
    assert state.tension_FU.shape == (7, 3)
    assert state.activation.shape == (7, 3)
    assert state.length_L0.shape == (7,)


def test_simulate_keeps_the_leading_shape_of_length():
    r1 = spindle.simulate(ramp(), 1e-3)
    r2 = spindle.simulate(np.stack([ramp(), ramp(0.11)], axis=1), 1e-3)
    assert r1.ia.shape == (1001,) and r2.ii.shape == (1001, 2)
    np.testing.assert_allclose(r2.ia[:, 0], r1.ia, atol=1e-9)


def test_sub_stepping_uses_the_method_default_and_honours_step():
    r = spindle.simulate(ramp(dt=2e-3), 2e-3)
    assert r.step_s == pytest.approx(1e-3)
    r = spindle.simulate(ramp(dt=2e-3), 2e-3, step=0.3e-3)
    assert r.step_s == pytest.approx(2e-3 / 7)


# -- bad input -------------------------------------------------------------------------


def assert_state_unchanged(state, before):
    for a, b in zip(state._arrays(), before._arrays(), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"length_L0": np.nan}, "length_L0 contains nan"),
        ({"length_L0": np.inf}, "length_L0 contains inf"),
        ({"length_L0": 0.45}, r"length_L0=0.45 is outside the model's range \[0.5, 1.5\]"),
        ({"length_L0": 1.6}, r"length_L0=1.6 is outside"),
        ({"gamma_dyn_pps": -1.0}, "gamma_dyn_pps=-1.0 is negative"),
        ({"gamma_stat_pps": np.nan}, "gamma_stat_pps contains nan"),
        ({"dt_s": 0.0}, "step=0.0 s must be finite and > 0"),
        ({"dt_s": -1e-3}, "must be finite and > 0"),
        ({"dt_s": 0.02}, "exceeds the trapezoidal limit of 0.01 s"),
        ({"length_L0": 1.05}, "above the limit"),  # 0.05 L0 in 1 ms = 50 L0/s
        ({"length_L0": np.ones(3)}, "does not broadcast to the 2 spindles"),
    ],
)
def test_step_refuses_bad_input_and_leaves_the_state_as_it_was(kwargs, message):
    state = spindle.equilibrium_state(np.array([1.0, 1.0]), 10.0, 10.0)
    before = state.copy()
    args = {"length_L0": 1.0, "gamma_dyn_pps": 10.0, "gamma_stat_pps": 10.0, "dt_s": 1e-3}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        spindle.step(state, **args)
    assert_state_unchanged(state, before)


def test_forward_euler_refuses_steps_beyond_its_stability_limit():
    limit = spindle.METHODS["forward_euler"].max_step_s
    state = spindle.equilibrium_state(1.0)
    with pytest.raises(ValueError, match="exceeds the forward_euler limit"):
        spindle.step(state, 1.0, 0.0, 0.0, limit * 1.5, method="forward_euler")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"length": np.array([1.0, np.nan, 1.0])}, "length_L0 contains nan"),
        ({"length": np.ones((3, 2, 2))}, r"shape \(T,\) or \(T, n\)"),
        ({"gamma_dyn": np.ones(4)}, "gamma_dyn has shape"),
        ({"gamma_stat": -np.ones(3)}, "gamma_stat_pps=-1.0 is negative"),
        ({"dt": 0.0}, "dt=0.0 s must be finite and > 0"),
        ({"step": 0.0}, "step=0.0 s must be finite"),
        ({"velocity": np.array([0.0, np.inf, 0.0]), "step": 1e-4}, "velocity contains"),
        ({"method": "rk4"}, "method='rk4' is not one of"),
    ],
)
def test_simulate_refuses_bad_input(kwargs, message):
    args = {"length": np.ones(3), "dt": 1e-3}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        spindle.simulate(args.pop("length"), args.pop("dt"), **args)


@pytest.mark.parametrize("length", [0.5, 1.5])
@pytest.mark.parametrize("drive", [0.0, 300.0])
def test_extreme_finite_inputs_give_finite_bounded_rates(length, drive):
    """Documented: at the range ends and 300 pps drive the model stays finite; a full-range
    swing at the speed limit too."""
    L = np.concatenate([np.full(50, 1.0), np.linspace(1.0, length, 60), np.full(300, length)])
    r = spindle.simulate(L, 1e-3, gamma_dyn=drive, gamma_stat=drive)
    assert np.isfinite(r.ia).all() and np.isfinite(r.ii).all()
    assert r.ia.min() >= 0 and r.ii.min() >= 0
    assert r.ia.max() < 2000 and r.ii.max() < 2000


def test_params_refuse_invalid_constants():
    with pytest.raises(ValueError, match=r"a=1\.2 must lie in"):
        dataclasses.replace(spindle.CAT.bag1, a=1.2)
    with pytest.raises(ValueError, match=r"tau_s=-0\.1"):
        dataclasses.replace(spindle.CAT.bag1, tau_s=-0.1)
    with pytest.raises(ValueError, match="factor=0"):
        spindle.CAT.scale_gains(0)
