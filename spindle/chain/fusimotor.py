"""The seed paper's fusimotor model: a motion template, h(x) for gamma-static, g(x) for
gamma-dynamic.

Fusimotor signals are taken to carry a "temporal template" of the expected movement. The
template of each muscle is the output of a down-sampled proportional-integral (PI) predictor
that tracks the muscle's length (or, through the chain's switch, its *intended* length):

- every ``1/predictor_rate_hz`` seconds the predictor compares its template p with the input
  length L, e = L - p, integrates it, w += ki e dt, and sets the template velocity
  u = kp e + w, which it holds until the next update; between updates p moves at u, so the
  template is continuous and piecewise linear;
- the integral w learns the current speed, so a steady movement is tracked without lag, and a
  sudden stop is overshot: the template runs on and comes back (the behaviour the paper
  describes). The loop is p'' = kp e' + ki e, a second-order system with natural frequency
  sqrt(ki) and damping kp / (2 sqrt(ki)).

From the template:

- h(x): gamma_s = 20 + 130 (Lmax - p)/(Lmax - Lmin) pps, clipped to 20..150 pps (the template
  can overshoot the muscle's range);
- g(x): gamma_d = 0 pps while the muscle shortens and 100 pps while it is static or
  lengthening. "Shortening" is decided by a time delay and a magnitude comparison: the muscle
  shortens when the template fell by more than ``shortening_threshold_L0`` over the last
  ``delay_s`` seconds, p(t - delay) - p(t) > threshold.

:class:`MotionPredictor` and :class:`Fusimotor` serve ``n`` arms at once, (n_arms, n_muscles)
arrays, each arm on its own update grid (one arm is ``n = 1``); their updates take a block
of k samples per arm (one sample is ``k = 1``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spindle.number_rule import check_fields


@dataclass(frozen=True)
class FusimotorParams:
    """Constants of the fusimotor model (defaults: the seed paper's values where it gives them).

    Attributes:
        gamma_static_min_pps, gamma_static_max_pps: range of h(x) (paper: 20 and 150 pps).
        gamma_dynamic_pps: g(x) while static or lengthening (paper: 100 pps; 0 pps while
            shortening).
        delay_s: g(x)'s time delay (s).
        shortening_threshold_L0: g(x)'s magnitude comparison (L0 over ``delay_s``); 0.002 L0
            in 40 ms is 0.05 L0/s, about 10 deg/s of elbow motion for the brachialis, well
            above the residual sensor noise after filtering.
        predictor_rate_hz: update rate of the down-sampled PI predictor (Hz).
        predictor_kp_1_s: proportional gain (1/s).
        predictor_ki_1_s2: integral gain (1/s^2). The defaults give a loop natural frequency
            of 2 Hz with damping 0.5: it follows a 130 deg/s movement and overshoots a
            sudden stop by a few percent of the movement, settling within about 0.5 s.
    """

    gamma_static_min_pps: float = 20.0
    gamma_static_max_pps: float = 150.0
    gamma_dynamic_pps: float = 100.0
    delay_s: float = 0.04
    shortening_threshold_L0: float = 0.002
    predictor_rate_hz: float = 50.0
    predictor_kp_1_s: float = 2.0 * 0.5 * (2.0 * math.pi * 2.0)
    predictor_ki_1_s2: float = (2.0 * math.pi * 2.0) ** 2

    def __post_init__(self) -> None:
        check_fields(self, ("gamma_static_min_pps", "gamma_dynamic_pps", "delay_s",
                            "shortening_threshold_L0", "predictor_kp_1_s",
                            "predictor_ki_1_s2"), low=0.0)
        check_fields(self, ("gamma_static_max_pps",), low=self.gamma_static_min_pps,
                     limit_note=f" (gamma_static_min_pps={self.gamma_static_min_pps!r})")
        check_fields(self, ("predictor_rate_hz",), low=0.0, low_open=True)
        # The discrete loop (held velocity, integral updated with the new error) has the
        # characteristic polynomial z^2 - (2 - a - b) z + (1 - a), a = kp dt, b = ki dt^2;
        # by Jury's test it is asymptotically stable iff a > 0, b > 0, a < 2 and 2a + b < 4.
        dt = 1.0 / self.predictor_rate_hz
        a, b = self.predictor_kp_1_s * dt, self.predictor_ki_1_s2 * dt * dt
        if not (a > 0 and b > 0 and a < 2 and 2 * a + b < 4):
            raise ValueError(
                f"predictor gains kp={self.predictor_kp_1_s!r} 1/s, ki="
                f"{self.predictor_ki_1_s2!r} 1/s^2 are not stable at {self.predictor_rate_hz!r}"
                f" Hz: need kp, ki > 0, kp*dt < 2 and 2*kp*dt + ki*dt^2 < 4 (dt = {dt!r} s)"
            )

    @property
    def predictor_period_s(self) -> float:
        return 1.0 / self.predictor_rate_hz


SEED_PAPER = FusimotorParams()
"""The seed paper's fusimotor model with the delay, threshold and PI gains documented above."""


def gamma_static_pps(
    length_L0: np.ndarray | float,
    length_min_L0: np.ndarray | float,
    length_max_L0: np.ndarray | float,
    params: FusimotorParams = SEED_PAPER,
) -> np.ndarray:
    """h(x): 20 + 130 (Lmax - L)/(Lmax - Lmin) pps, clipped to the gamma-static range."""
    lo = np.asarray(length_min_L0, dtype=float)
    hi = np.asarray(length_max_L0, dtype=float)
    if np.any(~(hi > lo)):
        raise ValueError(f"length_max_L0={hi!r} must exceed length_min_L0={lo!r}")
    span = params.gamma_static_max_pps - params.gamma_static_min_pps
    g = params.gamma_static_min_pps + span * (hi - np.asarray(length_L0, dtype=float)) / (hi - lo)
    return np.clip(g, params.gamma_static_min_pps, params.gamma_static_max_pps)


def gamma_dynamic_pps(
    length_now_L0: np.ndarray | float,
    length_delayed_L0: np.ndarray | float,
    params: FusimotorParams = SEED_PAPER,
) -> np.ndarray:
    """g(x): 0 pps if the length fell by more than the threshold over the delay, else 100."""
    fall = np.asarray(length_delayed_L0, dtype=float) - np.asarray(length_now_L0, dtype=float)
    return np.where(fall > params.shortening_threshold_L0, 0.0, params.gamma_dynamic_pps)


class MotionPredictor:
    """The down-sampled PI predictor of each muscle's length, for ``n`` independent arms:
    (n, n_muscles) arrays (one arm is ``n = 1``).

    Each arm's PI loop updates on its own grid of ``1/predictor_rate_hz`` from its own reset
    time. The last K updates (t_k, p_k, u_k) of each arm are kept in its row of (n, K) arrays,
    oldest first; a reset fills every slot with the rest segment (t_0, p_0, 0), which reads
    as one segment at every time. :meth:`update` takes a block of k samples per arm (k = 1:
    one sample each) and makes the PI updates due before each.
    """

    def __init__(self, params: FusimotorParams = SEED_PAPER, n: int = 1,
                 n_muscles: int = 2) -> None:
        self.params = params
        keep = math.ceil(params.delay_s * params.predictor_rate_hz) + 2
        self._t = np.zeros((n, keep))
        self._p = np.zeros((n, keep, n_muscles))
        self._u = np.zeros((n, keep, n_muscles))
        self._integral = np.zeros((n, n_muscles))

    def reset(self, t_s: np.ndarray, length_L0: np.ndarray,
              rows: np.ndarray | None = None) -> np.ndarray:
        """Arms ``rows`` (None: all) at rest at ``length_L0`` (r, m) at times ``t_s`` (r,);
        returns the templates (= the lengths)."""
        rows = slice(None) if rows is None else rows
        length_L0 = np.asarray(length_L0, dtype=float)
        self._t[rows] = np.asarray(t_s, dtype=float)[:, None]
        self._p[rows] = length_L0[:, None]
        self._u[rows] = 0.0
        self._integral[rows] = 0.0
        return length_L0.copy()

    @property
    def integral_L0_s(self) -> np.ndarray:
        """The integral terms w (n, m): each arm's estimate of its current speed (L0/s)."""
        return self._integral.copy()

    def update(self, t_s: np.ndarray, length_L0: np.ndarray, given: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """Feed every arm its inputs ``length_L0[i, j]`` (n, k, m) at times ``t_s[i, j]``
        (n, k) for the columns j where ``given[i, j]`` (None: all; each arm's given columns
        first, times increasing): returns (templates, templates ``delay_s`` earlier), each
        (n, k, m) (meaningless where not given). The input between PI updates is the latest
        sample: a sample-and-hold at the PI rate.

        The PI updates run in rounds (one per update of the arm with most; a block of one
        env step holds one or two), the templates of all columns then in a few gathers."""
        n, k = t_s.shape
        given = np.ones((n, k), dtype=bool) if given is None else given
        rounds, made, integral = self._pi_rounds(np.where(given, t_s, -math.inf), length_L0)
        keep = self._t.shape[1]
        width = keep + (int(made.max()) if rounds else 0)
        # each arm's kept updates then its new ones, oldest first: times (n, width) (+inf
        # past an arm's last), p and u (n, width, 2, m)
        T = np.full((n, width), math.inf)
        PU = np.empty((n, width, 2, *self._p.shape[2:]))
        T[:, :keep], PU[:, :keep, 0], PU[:, :keep, 1] = self._t, self._p, self._u
        newest = np.full((n, k), keep - 1)  # the newest update as of each column
        for i, j, slot, t_new, p_new, u_new in rounds:
            T[i, keep + slot], PU[i, keep + slot, 0], PU[i, keep + slot, 1] = (t_new, p_new,
                                                                                u_new)
            newest[i] += np.arange(k) >= j[:, None]
        # the delayed template: the newest of the `keep` updates kept at that column with a
        # time at or before t - delay (else the oldest kept); the updates made at later
        # columns lie after t (they were not due at t), so the search may run over the row
        back = t_s - self.params.delay_s
        at = np.maximum((T[:, None, :] <= back[..., None]).sum(axis=2) - 1,
                        newest - (keep - 1))
        base = (np.arange(n) * width)[:, None]
        which = np.stack((newest, at)) + base  # (2, n, k) flat indices
        t_at = T.reshape(-1).take(which)
        p_at, u_at = np.moveaxis(PU.reshape((n * width, *PU.shape[2:])).take(which, axis=0),
                                 3, 0)
        template = p_at[0] + u_at[0] * (t_s - t_at[0])[..., None]
        since = np.maximum(back - t_at[1], 0.0)
        delayed = p_at[1] + u_at[1] * since[..., None]
        if rounds:
            last = (base + made[:, None] + np.arange(keep)).reshape(-1)
            self._t = T.reshape(-1).take(last).reshape(n, keep)
            kept = PU.reshape((n * width, *PU.shape[2:])).take(last, axis=0)
            kept = kept.reshape((n, keep, *PU.shape[2:]))
            self._p, self._u = kept[:, :, 0].copy(), kept[:, :, 1].copy()
            self._integral = integral
        return template, delayed

    def _pi_rounds(self, times: np.ndarray, length_L0: np.ndarray) -> tuple[list, np.ndarray,
                                                                             np.ndarray]:
        """The PI updates due before the given ``times`` (n, k) (-inf: not given), in rounds:
        (arms, driving column, slot, t, p, u) of each round, the updates made per arm and
        the integral terms after them."""
        dt = self.params.predictor_period_s
        kp, ki = self.params.predictor_kp_1_s, self.params.predictor_ki_1_s2
        t_k = self._t[:, -1].copy()
        p = self._p[:, -1].copy()
        u = self._u[:, -1].copy()
        integral = self._integral.copy()
        made = np.zeros(times.shape[0], dtype=np.int64)
        rounds = []
        while True:
            due = times >= (t_k + dt * (1.0 - 1e-9))[:, None]
            i = np.flatnonzero(due.any(axis=1))
            if i.size == 0:
                break
            j = due[i].argmax(axis=1)  # the first column due: its input drives the update
            # at a clock so large (beyond 2^48 s) that t_k + dt rounds to t_k, the next
            # representable time: every update moves on, so the loop ends
            t_new = np.maximum(t_k[i] + dt, np.nextafter(t_k[i], math.inf))
            p_new = p[i] + dt * u[i]
            error = length_L0[i, j] - p_new
            w = integral[i] + (ki * dt) * error
            u_new = kp * error + w
            integral[i], t_k[i], p[i], u[i] = w, t_new, p_new, u_new
            rounds.append((i, j, made[i], t_new, p_new, u_new))
            made[i] += 1
        return rounds, made, integral

    def snapshot(self) -> tuple:
        """The predictors' state, for :meth:`restore` (a caller undoing a failed update)."""
        return tuple(a.copy() for a in (self._t, self._p, self._u, self._integral))

    def restore(self, snapshot: tuple) -> None:
        """Put back the state a :meth:`snapshot` of these predictors returned (once)."""
        self._t, self._p, self._u, self._integral = snapshot


class Fusimotor:
    """gamma_s and gamma_d of each muscle from its length, through the PI template, for ``n``
    independent arms: (n, n_muscles) arrays (one arm is ``n = 1``).

    Args:
        length_min_L0, length_max_L0: (n_muscles,) each muscle's range over the joint's range
            of motion (h(x)'s Lmin and Lmax; shared by the arms).
        params: :class:`FusimotorParams`.
        n: number of arms.
    """

    def __init__(self, length_min_L0: np.ndarray, length_max_L0: np.ndarray,
                 params: FusimotorParams = SEED_PAPER, n: int = 1) -> None:
        self.length_min_L0 = np.array(length_min_L0, dtype=float, ndmin=1)
        self.length_max_L0 = np.array(length_max_L0, dtype=float, ndmin=1)
        if np.any(~(self.length_max_L0 > self.length_min_L0)):
            raise ValueError(
                f"length_max_L0={self.length_max_L0!r} must exceed length_min_L0="
                f"{self.length_min_L0!r}"
            )
        self.params = params
        self.predictor = MotionPredictor(params, n, self.length_min_L0.size)

    def reset(self, t_s: np.ndarray, length_L0: np.ndarray,
              rows: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """Arms ``rows`` (None: all) at rest at ``length_L0`` (r, m) at ``t_s`` (r,):
        (template_L0, gamma_static_pps, gamma_dynamic_pps), each (r, m)."""
        template = self.predictor.reset(t_s, length_L0, rows)
        return self._rates(template, template)

    def update(self, t_s: np.ndarray, length_L0: np.ndarray, given: np.ndarray | None = None
               ) -> tuple[np.ndarray, ...]:
        """Feed the template's inputs ``length_L0`` (n, k, m) at ``t_s`` (n, k) where
        ``given`` (see :meth:`MotionPredictor.update`): (template_L0, gamma_s, gamma_d), each
        (n, k, m)."""
        return self._rates(*self.predictor.update(t_s, length_L0, given))

    def _rates(self, template: np.ndarray, delayed: np.ndarray) -> tuple[np.ndarray, ...]:
        return (
            template,
            gamma_static_pps(template, self.length_min_L0, self.length_max_L0, self.params),
            gamma_dynamic_pps(template, delayed, self.params),
        )
