"""An independent reference for the tendon organ step (scipy, imported lazily).

Built from its own statement of the model and nothing of :mod:`spindle.tendon_organ` but the
published constants: the whole linear part is the one transfer function

    G(s) = (b2 s^2 + b1 s + b0) / ((tau s + 1)(s^2 + a1 s + a0))

from r = G1 ln(F+/G2 + 1) to y, Ib = max(0, y). :func:`reference_rates` realises G with
``scipy.signal.tf2ss`` (scipy's own canonical form, not the step's) and integrates it with
``solve_ivp`` (Radau, rtol = atol = 1e-11) driven by r(F(t)) of a force given as a function of
continuous time, so the log is evaluated between samples too. :func:`step_response` is the
closed form of a force step from rest: partial fractions of G(s)/s (``scipy.signal.residue``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from spindle.tendon_organ_params import TendonOrganParams


def _transfer(params: TendonOrganParams) -> tuple[np.ndarray, np.ndarray]:
    num = np.array(params.num, dtype=float)
    den = np.polymul([params.tau_lowpass_s, 1.0], [1.0, *params.den])
    return num, den


def reference_rates(force_of_t: Callable[[float], float], t_s: np.ndarray,
                    force_scale_N: float, params: TendonOrganParams,
                    rtol: float = 1e-11, atol: float = 1e-11) -> np.ndarray:
    """Ib (pps) at times ``t_s`` (increasing, from t_s[0]) of one tendon organ at rest at
    ``force_of_t(t_s[0])`` and driven by the force function ``force_of_t`` (N)."""
    from scipy.integrate import solve_ivp
    from scipy.signal import tf2ss

    num, den = _transfer(params)
    A, B, C, D = tf2ss(num, den)
    b = B[:, 0]

    def r(t: float) -> float:
        return params.gain_pps * np.log1p(max(force_of_t(t), 0.0) / force_scale_N)

    x0 = np.linalg.solve(A, -b * r(float(t_s[0])))  # rest: A x + b r = 0
    sol = solve_ivp(lambda t, x: A @ x + b * r(t), (float(t_s[0]), float(t_s[-1])), x0,
                    method="Radau", t_eval=t_s, rtol=rtol, atol=atol, max_step=0.01)
    if not sol.success:
        raise RuntimeError(f"solve_ivp failed: {sol.message}")
    y = (C @ sol.y)[0] + D[0, 0] * np.array([r(float(t)) for t in t_s])
    return np.maximum(y, 0.0)


def step_response(t_s: np.ndarray, force_before_N: float, force_after_N: float,
                  force_scale_N: float, params: TendonOrganParams) -> np.ndarray:
    """Closed form Ib (pps) at ``t_s`` >= 0 after a force step at t = 0 from rest at
    ``force_before_N`` to ``force_after_N``: r0 H(0) + (r1 - r0) * (step response of G)."""
    from scipy.signal import residue

    num, den = _transfer(params)
    r0, r1 = (params.gain_pps * np.log1p(max(f, 0.0) / force_scale_N)
              for f in (force_before_N, force_after_N))
    # G(s)/s = sum_i res_i / (s - p_i): the step response is sum_i res_i e^{p_i t}
    res, poles, direct = residue(num, np.polymul(den, [1.0, 0.0]))
    if np.size(direct) and np.any(direct != 0):
        raise ValueError("G(s)/s is not strictly proper")
    t = np.asarray(t_s, dtype=float)[:, None]
    unit = np.real(np.sum(res[None, :] * np.exp(poles[None, :] * t), axis=1))
    return np.maximum(r0 * params.num[2] / params.den[1] + (r1 - r0) * unit, 0.0)
