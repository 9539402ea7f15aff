"""Behaviour of the spindle model and its theta-method core.

The expected behaviour comes from the model's definition (Mileusnic et al. 2006) and the
seed paper, not from recorded outputs: closed-form equilibria, the preset relation, monotone
responses, batching, and refusal of bad input.
"""

import dataclasses

import numpy as np
import pytest

import spindle
from spindle import batch_step, core

METHODS = sorted(spindle.METHODS)


def ramp(speed_L0_s=0.66, dt=1e-3, start=0.95, end=1.08, t_ramp=0.3, duration=1.0):
    t = np.arange(0, duration + dt / 2, dt)
    return np.clip(start + speed_L0_s * (t - t_ramp), start, end)


def test_equilibrium_tension_balances_the_fibre_forces():
    state = spindle.equilibrium_state(np.array([0.8, 1.0, 1.2]), 50.0, 80.0)
    c = core.columns(spindle.CAT)
    T = state.tension_FU.T
    f = state.activation.T
    force = core.force(T, state.velocity_root.T, state.length_L0, f, c)
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
        ({"dt_s": 0.0}, "dt_s=0.0 must be a finite real number > 0"),
        ({"dt_s": -1e-3}, "must be a finite real number > 0"),
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
        ({"dt": 0.0}, "dt=0.0 must be a finite real number > 0"),
        ({"step": 0.0}, "step=0.0 must be a finite real number"),
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


# -- the optimised step against a plain reference step ------------------------------------


def reference_advance(state, L1, gd1, gs1, h, theta, params=spindle.CAT):
    """The step written plainly from the model equations (``core.plain_advance``)."""
    return core.plain_advance(state, L1, gd1, gs1, h, theta, core.columns(params))


@pytest.mark.parametrize("theta", [0.0, 0.5, 1.0])
def test_the_plain_step_solves_the_theta_method_equations(theta):
    """The plain step's result satisfies the theta-method's equations, term by term:
    T1 = T0 + KSR*(L1 - L0) - h*KSR*((1 - theta)*v0 + theta*v1), M*(v1 - v0)/h =
    (1 - theta)*F0 + theta*F1, (f1 - f0)/h = ((1 - theta)*(a0 - f0) + theta*(a1 - f1))/tau
    (f1 = a1 where tau = 0) and z1 = sgn(v1)|v1|^(a/3)."""
    n = 40
    h = 1e-3 if theta else 2e-5
    state, L1, gd1, gs1 = random_states(n, seed=17)
    if not theta:
        L1 = state.length_L0 + (L1 - state.length_L0) * 0.02
    c = core.columns(spindle.CAT)
    T1, v1, z1, f1 = core.plain_advance(state, L1, gd1, gs1, h, theta, c)
    T0, v0, z0, f0 = (a.T for a in (state.tension_FU, state.polar_velocity_L0_s,
                                     state.velocity_root, state.activation))
    L0 = state.length_L0
    np.testing.assert_allclose(
        T1, T0 + c.KSR * (L1 - L0) - h * c.KSR * ((1 - theta) * v0 + theta * v1),
        rtol=0, atol=1e-14)

    def force(T, z, L, f):
        polar = L - c.LSR0 - T / c.KSR
        damping = np.where(z > 0, c.CL, c.CS) * (c.beta0 + c.beta_drive * f) * z**3
        return (T - c.Gamma_drive * f - c.KPR * (polar - c.LPR0)
                - damping * np.maximum(polar - c.R, 0.0))

    np.testing.assert_allclose(
        c.M * (v1 - v0) / h, (1 - theta) * force(T0, z0, L0, f0) + theta * force(T1, z1, L1, f1),
        rtol=0, atol=1e-10)

    def target(gd, gs):
        g = np.stack((gd, gs, gs)) ** c.p
        return g / (g + c.freq**c.p)

    a0, a1 = target(state.gamma_dyn_pps, state.gamma_stat_pps), target(gd1, gs1)
    lagged = c.lagged
    np.testing.assert_allclose(
        (f1 - f0)[lagged],
        (h * ((1 - theta) * (a0 - f0) + theta * (a1 - f1)) / c.tau_safe)[lagged], rtol=0,
        atol=1e-15)
    # the unlagged fibre takes its target: the same expression, evaluated in another order
    # by the step (numpy 2.4 rounds it up to 2.2e-16 relative apart; 1 ulp)
    np.testing.assert_allclose(f1[~lagged], a1[~lagged], rtol=5e-16, atol=0)
    np.testing.assert_allclose(np.sign(z1) * np.abs(z1) ** (3 / c.a), v1, rtol=1e-12, atol=0)


def random_states(n, seed):
    """Spindles in random but valid states: lengths, drives, tensions off equilibrium, and
    polar velocities from exactly 0 through tiny to ~1 L0/s of either sign."""
    rng = np.random.default_rng(seed)
    L = rng.uniform(0.75, 1.25, n)
    state = spindle.equilibrium_state(L, rng.uniform(0, 150, n), rng.uniform(0, 150, n))
    v = rng.choice([0.0, 1e-9, 1e-4, 0.02, 0.5, 1.2], size=(n, 3)) * rng.choice([-1, 1], (n, 3))
    state.polar_velocity_L0_s[...] = v
    state.velocity_root[...] = np.sign(v) * np.abs(v) ** 0.1
    state.tension_FU[...] += rng.normal(0, 0.01, (n, 3))
    state.activation[...] = np.clip(state.activation + rng.normal(0, 0.05, (n, 3)), 0, 1)
    # half keep their drive over the step, half change it
    gd1 = np.where(rng.random(n) < 0.5, state.gamma_dyn_pps, rng.uniform(0, 150, n))
    gs1 = np.where(rng.random(n) < 0.5, state.gamma_stat_pps, rng.uniform(0, 150, n))
    L1 = L + rng.uniform(-1.5e-3, 1.5e-3, n)
    return state, L1, gd1, gs1


@pytest.mark.parametrize("theta", [0.5, 1.0, 0.0])
@pytest.mark.parametrize("n", [1, 3, 6, batch_step.CHUNK_SPINDLES + 37])
@pytest.mark.parametrize("h", [1e-3, 1e-4])
def test_optimised_step_matches_the_plain_reference_step(theta, n, h):
    state, L1, gd1, gs1 = random_states(n, seed=n)
    before = state.copy()
    c = core.columns(spindle.CAT)
    T1, v1, z1, f1 = core.advance(state, L1, gd1, gs1, h, theta, c)
    assert_state_unchanged(state, before)
    T_ref, v_ref, z_ref, f_ref = reference_advance(state, L1, gd1, gs1, h, theta)
    np.testing.assert_allclose(f1, f_ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(v1, v_ref, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(T1, T_ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.sign(z1) * np.abs(z1) ** 10, v1, rtol=1e-13, atol=0)
    np.testing.assert_allclose(z1, z_ref, rtol=0, atol=1e-9 if theta else 1e-12)
    ia, ii = core.afferents_from_tension(T1, L1, c)
    ia_ref, ii_ref = core.afferents_from_tension(T_ref, L1, c)
    np.testing.assert_allclose(ia, ia_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ii, ii_ref, rtol=0, atol=1e-9)


@pytest.mark.parametrize("theta", [0.5, 1.0])
@pytest.mark.parametrize(("n", "chunk"), [(2, None), (9, None), (300, None), (3001, 1000)])
def test_a_step_size_per_spindle_matches_the_plain_reference_step(monkeypatch, theta, n, chunk):
    """Each spindle its own h (arms sampled at their own times), in one call of the fast
    step (in one block or several): the plain step's result to the tolerances above, and
    with every h equal, the result of the scalar-h step."""
    if chunk is not None:
        monkeypatch.setattr(batch_step, "CHUNK_SPINDLES", chunk)
    state, L1, gd1, gs1 = random_states(n, seed=n + 5)
    h = np.random.default_rng(n).uniform(2e-4, 1e-3, n)
    before = state.copy()
    c = core.columns(spindle.CAT)
    T1, v1, z1, f1 = (x.copy() for x in core.advance(state, L1, gd1, gs1, h, theta, c))
    assert_state_unchanged(state, before)
    T_ref, v_ref, z_ref, f_ref = reference_advance(state, L1, gd1, gs1, h, theta)
    np.testing.assert_allclose(f1, f_ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(v1, v_ref, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(T1, T_ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(z1, z_ref, rtol=0, atol=1e-9)
    same = np.full(n, 7e-4)
    each = [x.copy() for x in core.advance(state, L1, gd1, gs1, same, theta, c)]
    one = core.advance(state, L1, gd1, gs1, 7e-4, theta, c)
    for got, want in zip(each, one, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("method", ["trapezoidal", "backward_euler"])
def test_optimised_trajectory_stays_on_the_reference_trajectory(method):
    """300 steps of 1 ms along random smooth inputs, both started at rest: the afferent rates
    of the optimised core stay within 1e-9 pps of the plain reference step."""
    rng = np.random.default_rng(11)
    n = 40
    t = np.arange(301)[:, None] * 1e-3
    L = 1.0 + 0.1 * np.sin(2 * np.pi * rng.uniform(0.5, 4, n) * t) * rng.uniform(0, 1, n)
    gd = 60 * (1 + np.sin(2 * np.pi * rng.uniform(0.2, 2, n) * t))
    gs = np.full_like(L, 40.0)
    theta = spindle.METHODS[method].theta
    c = core.columns(spindle.CAT)
    fast = spindle.equilibrium_state(L[0], gd[0], gs[0])
    plain = fast.copy()
    worst = 0.0
    for i in range(1, L.shape[0]):
        core.commit(fast, core.advance(fast, L[i], gd[i], gs[i], 1e-3, theta, c),
                    L[i], gd[i], gs[i])
        core.commit(plain, reference_advance(plain, L[i], gd[i], gs[i], 1e-3, theta),
                    L[i], gd[i], gs[i])
        rates = np.concatenate(spindle.afferents(fast))
        rates_ref = np.concatenate(spindle.afferents(plain))
        worst = max(worst, np.abs(rates - rates_ref).max())
    assert worst < 1e-9
    assert np.abs(plain.polar_velocity_L0_s).max() > 0.05  # the test did move the spindles


def _history_steers_the_step(state, L1, gd1, gs1, h, c) -> bool:
    """Whether the next step from ``state`` differs, bit for bit, from the same step from a
    fresh copy of it (no step history, so the frozen-factor guess). Newton converges to the
    same tolerance from either guess, but not to the same last bits. ``state`` is unchanged."""
    fresh = state.copy()
    steered = [a.copy() for a in core.advance(state, L1, gd1, gs1, h, 0.5, c)]
    plain = core.advance(fresh, L1, gd1, gs1, h, 0.5, c)
    for got, want in zip(steered, plain, strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    return not all(np.array_equal(a, b) for a, b in zip(steered, plain, strict=True))


def test_extrapolated_guess_survives_a_state_changed_between_steps(monkeypatch):
    """From the fourth step on, the numpy path guesses z by extrapolating its own last outputs.
    Resetting half the spindles, an uncommitted step and a step of another size in between
    must not move the result off the plain reference step (they may only cost iterations),
    over two blocks and a remainder."""
    # This motion's first extrapolated step needs more than EXTRAPOLATE_MAX_ITER iterations,
    # which would switch extrapolation off for the rest of the test: keep it on.
    monkeypatch.setattr(batch_step, "EXTRAPOLATE_COOLDOWN", 0)
    rng = np.random.default_rng(21)
    n = batch_step.EXTRAPOLATE_SPINDLES + 37
    assert n > batch_step.CHUNK_SPINDLES
    steps = 24
    t = np.arange(steps + 1)[:, None] * 1e-3
    L = 1.0 + 0.08 * np.sin(2 * np.pi * rng.uniform(1, 4, n) * t + rng.uniform(0, 6, n))
    gd = 50 * (1 + np.sin(2 * np.pi * rng.uniform(0.5, 2, n) * t))
    gs = np.full(n, 30.0)
    c = core.columns(spindle.CAT)
    fast = spindle.equilibrium_state(L[0], gd[0], gs)
    plain = fast.copy()
    worst = 0.0
    for i in range(1, steps + 1):
        h = 0.5e-3 if i == 17 else 1e-3
        if i == 9:  # reset half the spindles in place, as a user may
            half = slice(0, n, 2)
            for state in (fast, plain):
                fresh = spindle.equilibrium_state(L[i - 1][half] + 0.05, 80.0, 30.0)
                for mine, new in zip(state._arrays(), fresh._arrays(), strict=True):
                    mine[half] = new
        if i == 13:  # a step taken and thrown away
            core.advance(fast, L[i] + 0.01, gd[i], gs, h, 0.5, c)
        core.commit(fast, core.advance(fast, L[i], gd[i], gs, h, 0.5, c), L[i], gd[i], gs)
        core.commit(plain, reference_advance(plain, L[i], gd[i], gs, h, 0.5), L[i], gd[i], gs)
        rates = np.concatenate(spindle.afferents(fast))
        rates_ref = np.concatenate(spindle.afferents(plain))
        worst = max(worst, np.abs(rates - rates_ref).max())
    assert worst < 1e-9
    # the last steps extrapolated: the next step's result depends on the state's history
    assert _history_steers_the_step(fast, 2 * L[-1] - L[-2], gd[-1], gs, 1e-3, c)


def test_noisy_lengths_send_the_guess_back_to_the_frozen_factor():
    """Length noise of 1e-4 L0 per 1 ms sample makes the extrapolated z ring: the blocks
    then need more than EXTRAPOLATE_MAX_ITER Newton iterations, and the workspace returns to
    the frozen-factor guess for a while. Either way the result is the reference step's."""
    rng = np.random.default_rng(5)
    n = batch_step.EXTRAPOLATE_SPINDLES
    steps = 6
    L = 1.0 + rng.normal(0.0, 1e-4, (steps + 1, n))
    gd, gs = np.full(n, 40.0), np.full(n, 40.0)
    c = core.columns(spindle.CAT)
    fast = spindle.equilibrium_state(L[0], gd, gs)
    plain = fast.copy()
    for i in range(1, steps + 1):
        core.commit(fast, core.advance(fast, L[i], gd, gs, 1e-3, 0.5, c), L[i], gd, gs)
        core.commit(plain, reference_advance(plain, L[i], gd, gs, 1e-3, 0.5), L[i], gd, gs)
    # back on the frozen-factor guess: the next step is the one a fresh copy of the state takes
    assert not _history_steers_the_step(fast, L[-1], gd, gs, 1e-3, c)
    np.testing.assert_allclose(np.concatenate(spindle.afferents(fast)),
                               np.concatenate(spindle.afferents(plain)), rtol=0, atol=1e-9)


@pytest.mark.parametrize("theta", [0.5, 1.0])
def test_few_spindle_float_path_equals_the_vectorised_path(theta):
    """The Python-float path (n <= SMALL_N) and the numpy path give the same step."""
    n = 2 * core.SMALL_N + 1
    state, L1, gd1, gs1 = random_states(n, seed=5)
    c = core.columns(spindle.CAT)
    vectorised = [a.copy() for a in core.advance(state, L1, gd1, gs1, 1e-3, theta, c)]
    for j in range(0, n, core.SMALL_N):
        cols = slice(j, j + core.SMALL_N)
        sub = core.SpindleState(*(a[cols].copy() for a in state._arrays()))
        assert sub.n <= core.SMALL_N
        small = core.advance(sub, L1[cols], gd1[cols], gs1[cols], 1e-3, theta, c)
        for got, want in zip(small, vectorised, strict=True):
            np.testing.assert_allclose(got, want[:, cols], rtol=1e-12, atol=1e-14)
        rates = core.afferents_from_tension(small[0], L1[cols], c)
        rates_vectorised = core.afferents_from_tension(vectorised[0][:, cols], L1[cols], c)
        for got, want in zip(rates, rates_vectorised, strict=True):
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)


@pytest.mark.parametrize(("chunk", "tail"), [(None, True), (1000, True), (None, False)])
def test_slow_fibres_finished_in_the_common_tail_match_the_reference(monkeypatch, chunk, tail):
    """Fibres whose v reverses need more Newton iterations than the rest of their block; the
    block hands them on and they are finished together (from TAIL_MIN_SPINDLES on), or the
    block iterates on. Still the reference result."""
    if chunk is not None:
        monkeypatch.setattr(batch_step, "CHUNK_SPINDLES", chunk)
    if not tail:
        monkeypatch.setattr(batch_step, "TAIL_MIN_SPINDLES", 10**9)
    n = 3000
    state, L1, gd1, gs1 = random_states(n, seed=9)
    # mostly at rest and held: quick convergence; a few reverse a fast polar velocity
    state.polar_velocity_L0_s[...] = 0.0
    state.velocity_root[...] = 0.0
    L1 = state.length_L0.copy()
    gd1, gs1 = state.gamma_dyn_pps.copy(), state.gamma_stat_pps.copy()
    fast = np.arange(0, n, 97)
    state.polar_velocity_L0_s[fast] = 1.5
    state.velocity_root[fast] = 1.5**0.1
    calls = []
    finish_tail = batch_step.Workspace._finish_tail
    monkeypatch.setattr(batch_step.Workspace, "_finish_tail",
                        lambda self, tail, **kw: calls.append(len(tail))
                        or finish_tail(self, tail, **kw))
    c = core.columns(spindle.CAT)
    T1, v1, _, _ = core.advance(state, L1, gd1, gs1, 1e-3, 0.5, c)
    assert bool(calls) == tail, calls
    T_ref, v_ref, _, _ = reference_advance(state, L1, gd1, gs1, 1e-3, 0.5)
    np.testing.assert_allclose(v1, v_ref, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(T1, T_ref, rtol=0, atol=1e-13)


@pytest.mark.parametrize("n", [1, 50])
def test_a_non_finite_step_raises_and_leaves_the_state_as_it_was(n):
    state = spindle.equilibrium_state(np.full(n, 1.0), 20.0, 20.0)
    state.velocity_root[0, 1] = np.nan
    before = state.copy()
    with pytest.raises(FloatingPointError):
        spindle.step(state, 1.0, 20.0, 20.0, 1e-3)
    for a, b in zip(state._arrays(), before._arrays(), strict=True):
        np.testing.assert_array_equal(a, b)


def test_advance_output_is_valid_until_the_next_advance():
    """advance returns reused buffers; commit copies them, so later steps do not alter the
    committed state."""
    state = spindle.equilibrium_state(np.linspace(0.9, 1.1, 20))
    c = core.columns(spindle.CAT)
    new = core.advance(state, state.length_L0 + 1e-3, 0.0, 0.0, 1e-3, 0.5, c)
    core.commit(state, new, state.length_L0 + 1e-3, 0.0, 0.0)
    kept = state.copy()
    core.advance(state, state.length_L0 + 1e-3, 50.0, 0.0, 1e-3, 0.5, c)
    assert_state_unchanged(state, kept)


@pytest.mark.parametrize("extra", [{}, {"velocity": "v"}, {"velocity": "v", "acceleration": "a"}])
@pytest.mark.parametrize("dt", [1e-3, 2.5e-3])
def test_simulate_one_spindle_float_loop_equals_the_array_loop(extra, dt):
    """simulate runs one spindle on floats; the same trace as two columns takes the array
    loop. Both interpolate and step alike, with or without sub-steps and derivatives."""
    t = np.arange(0, 0.5, dt)
    L = 1.0 + 0.08 * np.sin(2 * np.pi * 1.7 * t) ** 3
    v = np.gradient(L, dt)
    kwargs = {name: {"v": v, "a": np.gradient(v, dt)}[x] for name, x in extra.items()}
    one = spindle.simulate(L, dt, gamma_dyn=40.0 + 20 * np.cos(9 * t), gamma_stat=30.0,
                           **kwargs)
    two = spindle.simulate(np.stack([L, L], axis=1), dt,
                           gamma_dyn=(40.0 + 20 * np.cos(9 * t))[:, None], gamma_stat=30.0,
                           **{name: np.stack([x, x], axis=1) for name, x in kwargs.items()})
    assert one.step_s == two.step_s
    np.testing.assert_allclose(two.ia[:, 0], one.ia, rtol=0, atol=1e-9)
    np.testing.assert_allclose(two.ii[:, 1], one.ii, rtol=0, atol=1e-9)
    assert one.ia.max() > 50


def reference_afferents(T, L, params):
    """Ia and II straight from the model's definitions (Mileusnic 2006, eqs. for the
    primary and secondary potentials), term by term."""
    f = params.fibres
    stretch = [T[i] / f[i].KSR_FU_L0 - (f[i].LNSR_L0 - f[i].LSR0_L0) for i in range(3)]
    primary = [np.maximum(f[i].G_primary_pps_L0 * stretch[i], 0.0) for i in range(3)]
    a_dyn, b_stat = primary[0], primary[1] + primary[2]
    ia = np.maximum(a_dyn, b_stat) + params.S * np.minimum(a_dyn, b_stat)
    ii = sum(
        np.maximum(f[i].G_secondary_pps_L0 * (
            f[i].X * f[i].Lsec_L0 / f[i].LSR0_L0 * stretch[i]
            + (1 - f[i].X) * f[i].Lsec_L0 / f[i].LPR0_L0
            * (L - T[i] / f[i].KSR_FU_L0 - f[i].LSR0_L0 - f[i].LNPR_L0)), 0.0)
        for i in (1, 2))
    return ia, ii


@pytest.mark.parametrize("n", [1, 4, 5, core.AFFERENT_CHUNK + 11])
@pytest.mark.parametrize("params", [spindle.CAT, spindle.HUMAN])
def test_afferents_match_the_model_definitions(n, params):
    rng = np.random.default_rng(n)
    # tensions from slack (negative potentials, clipped) to well stretched
    T = rng.uniform(-0.05, 0.5, (3, n))
    L = rng.uniform(0.5, 1.5, n)
    ia, ii = core.afferents_from_tension(T, L, core.columns(params))
    ia_ref, ii_ref = reference_afferents(T, L, params)
    assert ia.shape == ii.shape == (n,)
    np.testing.assert_allclose(ia, ia_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ii, ii_ref, rtol=0, atol=1e-9)
    assert (ia == 0).any() or n < 10  # the clipping is exercised


@pytest.mark.parametrize("n", [2, 300])
def test_optimised_step_with_another_damping_exponent_matches_the_reference(n):
    """a != 0.3 takes the general power path of the solver (v = sgn(z)|z|^(3/a))."""
    params = dataclasses.replace(
        spindle.CAT, bag1=dataclasses.replace(spindle.CAT.bag1, a=0.25),
        bag2=dataclasses.replace(spindle.CAT.bag2, a=0.35))
    state, L1, gd1, gs1 = random_states(n, seed=2)
    c = core.columns(params)
    a = c.a[:, 0][None, :]
    state.velocity_root[...] = (np.sign(state.polar_velocity_L0_s)
                                * np.abs(state.polar_velocity_L0_s) ** (a / 3))
    T1, v1, z1, _ = core.advance(state, L1, gd1, gs1, 1e-3, 0.5, c)
    T_ref, v_ref, _, _ = reference_advance(state, L1, gd1, gs1, 1e-3, 0.5, params)
    np.testing.assert_allclose(v1, v_ref, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(T1, T_ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.sign(z1) * np.abs(z1) ** (3 / a.T), v1, rtol=1e-12)


def test_any_memory_layout_of_the_state_and_copies_without_the_scratch_buffers():
    """A state built by hand from (n, 3) C-ordered arrays (not views of fibre-major
    buffers) steps like the same state from equilibrium_state; pickling and deep copies
    leave the step's reused buffers behind."""
    import copy
    import pickle

    state, L1, gd1, gs1 = random_states(50, seed=4)
    by_hand = core.SpindleState(*(np.ascontiguousarray(a) for a in state._arrays()))
    assert not by_hand.tension_FU.T.flags.c_contiguous
    c = core.columns(spindle.CAT)
    want = [a.copy() for a in core.advance(state, L1, gd1, gs1, 1e-3, 0.5, c)]
    got = core.advance(by_hand, L1, gd1, gs1, 1e-3, 0.5, c)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    assert "_workspace" in state.__dict__
    for clone in (pickle.loads(pickle.dumps(state)), copy.deepcopy(state)):
        assert "_workspace" not in clone.__dict__
        assert_state_unchanged(clone, state)


@pytest.mark.parametrize("n", [2, 30])
def test_a_step_that_changes_from_call_to_call_matches_the_reference(n):
    """A streaming chain's sample interval jitters, so h differs at every step: the
    per-step constants follow it."""
    rng = np.random.default_rng(8)
    c = core.columns(spindle.CAT)
    state, _, _, _ = random_states(n, seed=3)
    plain = state.copy()
    for h in 1e-3 * (1 + rng.uniform(-0.2, 0.2, 30)):
        L1 = state.length_L0 + rng.uniform(-5e-4, 5e-4, n)
        gd1 = state.gamma_dyn_pps + 1.0
        core.commit(state, core.advance(state, L1, gd1, state.gamma_stat_pps, h, 0.5, c),
                    L1, gd1, state.gamma_stat_pps)
        core.commit(plain, reference_advance(plain, L1, gd1, plain.gamma_stat_pps, h, 0.5),
                    L1, gd1, plain.gamma_stat_pps)
    np.testing.assert_allclose(np.concatenate(spindle.afferents(state)),
                               np.concatenate(spindle.afferents(plain)), rtol=0, atol=1e-9)


@pytest.mark.parametrize("theta", [0.5, 1.0])
@pytest.mark.parametrize("params", [spindle.CAT, spindle.HUMAN], ids=["cat", "human"])
def test_step_constants_per_spindle_equal_the_float_constants_of_each_step(theta, params):
    """Every constant of a step with a size per spindle (built with array operations) equals,
    spindle by spindle, the constant the float path builds for that step size alone."""
    from dataclasses import fields

    from spindle.fibre_constants import SpindleStepConstants, StepConstants

    c = core.columns(params)
    h = np.random.default_rng(3).uniform(1e-5, 2e-3, 7)
    each = SpindleStepConstants(c, h, theta)
    for j, hj in enumerate(h):
        one = StepConstants(c, float(hj), theta)
        for i in range(3):
            for f in fields(type(one.fibre[i])):
                want = getattr(one.fibre[i], f.name)
                got = np.broadcast_to(getattr(each.fibre_columns, f.name), (3, h.size))[i, j]
                assert got == pytest.approx(want, rel=1e-14, abs=1e-300), (f.name, i, hj)
                row = np.broadcast_to(getattr(each.fibre[i], f.name), h.shape)
                assert row[j] == got, (f.name, i, hj)
