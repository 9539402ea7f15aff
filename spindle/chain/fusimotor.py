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

:class:`MotionPredictor` and :class:`Fusimotor` serve one arm (arrays over muscles);
:class:`BatchedMotionPredictor` and :class:`BatchedFusimotor` serve many arms at once,
(n_arms, n_muscles) arrays, each arm on its own update grid.
"""

from __future__ import annotations

import math
from collections import deque
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
    """The down-sampled PI predictor of each muscle's length (vectorised over muscles).

    :meth:`update` may be called at any rate (e.g. every sensor sample); the PI loop itself
    updates on its own grid of ``1/predictor_rate_hz`` starting at the reset time.

    (The batched arms' loop is :class:`BatchedMotionPredictor`, the same arithmetic. This one on
    a deque of (2,) arrays stays: the single chain built on ``BatchedMotionPredictor(1, 2)``
    and ``BatchedMedianFilter(1)`` pushed bit-identical outputs 1.16-1.26x slower, side by
    side on an idle 2-core machine (1.3-1.6x loaded), 2026-12-01.)
    """

    def __init__(self, params: FusimotorParams = SEED_PAPER) -> None:
        self.params = params
        n_keep = math.ceil(params.delay_s * params.predictor_rate_hz) + 2
        # (t_k, p_k, u_k) of the last updates: enough segments to look back by delay_s.
        self._segments: deque[tuple[float, np.ndarray, np.ndarray]] = deque(maxlen=n_keep)
        self._integral = np.zeros(0)

    def reset(self, t_s: float, length_L0: np.ndarray) -> np.ndarray:
        """At rest at ``length_L0`` at time ``t_s``; returns the template (= the length)."""
        p = np.array(length_L0, dtype=float, ndmin=1)
        self._segments.clear()
        self._segments.append((float(t_s), p, np.zeros_like(p)))
        self._integral = np.zeros_like(p)
        return p.copy()

    @property
    def integral_L0_s(self) -> np.ndarray:
        """The integral term w: the predictor's estimate of the current speed (L0/s)."""
        return self._integral.copy()

    def update(self, t_s: float, length_L0: np.ndarray) -> np.ndarray:
        """Feed the input length at time ``t_s`` (non-decreasing); return the template."""
        if not self._segments:
            raise RuntimeError("MotionPredictor.update before reset")
        dt = self.params.predictor_period_s
        kp, ki = self.params.predictor_kp_1_s, self.params.predictor_ki_1_s2
        t_k, p, u = self._segments[-1]
        # The input between updates is the latest sample: a sample-and-hold at the PI rate.
        while t_s >= t_k + dt * (1.0 - 1e-9):
            # At a clock so large (beyond 2^48 s) that t_k + dt rounds to t_k, the next
            # representable time: every update moves on, so the loop ends.
            t_k = max(t_k + dt, math.nextafter(t_k, math.inf))
            p = p + dt * u
            error = length_L0 - p
            self._integral = self._integral + (ki * dt) * error
            u = kp * error + self._integral
            self._segments.append((t_k, p, u))
        return p + u * (t_s - t_k)

    def snapshot(self) -> tuple:
        """The predictor's state, for :meth:`restore` (a caller undoing a failed update)."""
        return tuple(self._segments), self._integral

    def restore(self, snapshot: tuple) -> None:
        """Put back the state a :meth:`snapshot` of this predictor returned."""
        segments, self._integral = snapshot
        self._segments.clear()
        self._segments.extend(segments)

    def template_at(self, t_s: float) -> np.ndarray:
        """The template at an earlier time ``t_s`` (clamped to the oldest kept update)."""
        for t_k, p, u in reversed(self._segments):
            if t_k <= t_s:
                return p + u * (t_s - t_k)
        return self._segments[0][1].copy()


class Fusimotor:
    """gamma_s and gamma_d of each muscle from its length, through the PI template.

    Args:
        length_min_L0, length_max_L0: (n_muscles,) the range of each muscle over the joint's
            range of motion (h(x)'s Lmin and Lmax).
        params: :class:`FusimotorParams`.
    """

    def __init__(
        self,
        length_min_L0: np.ndarray,
        length_max_L0: np.ndarray,
        params: FusimotorParams = SEED_PAPER,
    ) -> None:
        self.length_min_L0 = np.array(length_min_L0, dtype=float, ndmin=1)
        self.length_max_L0 = np.array(length_max_L0, dtype=float, ndmin=1)
        if np.any(~(self.length_max_L0 > self.length_min_L0)):
            raise ValueError(
                f"length_max_L0={self.length_max_L0!r} must exceed length_min_L0="
                f"{self.length_min_L0!r}"
            )
        self.params = params
        self.predictor = MotionPredictor(params)

    def reset(self, t_s: float, length_L0: np.ndarray) -> tuple[np.ndarray, ...]:
        """At rest: returns (template_L0, gamma_static_pps, gamma_dynamic_pps)."""
        template = self.predictor.reset(t_s, length_L0)
        return self._rates(t_s, template)

    def update(self, t_s: float, length_L0: np.ndarray) -> tuple[np.ndarray, ...]:
        """Feed the template's input at ``t_s``; returns (template_L0, gamma_s, gamma_d)."""
        template = self.predictor.update(t_s, np.asarray(length_L0, dtype=float))
        return self._rates(t_s, template)

    def _rates(self, t_s: float, template: np.ndarray) -> tuple[np.ndarray, ...]:
        delayed = self.predictor.template_at(t_s - self.params.delay_s)
        return (
            template,
            gamma_static_pps(template, self.length_min_L0, self.length_max_L0, self.params),
            gamma_dynamic_pps(template, delayed, self.params),
        )


class BatchedMotionPredictor:
    """:class:`MotionPredictor` for ``n`` independent arms: (n, n_muscles) arrays.

    Each arm's PI loop updates on its own grid of ``1/predictor_rate_hz`` from its own reset
    time, with the same arithmetic as :class:`MotionPredictor` (so the same bits). The last
    K updates (t_k, p_k, u_k) of each arm are kept in its row of (n, K) arrays, oldest first;
    a reset fills every slot with the rest segment (t_0, p_0, 0), which reads as the single
    predictor's one segment at every time. ``rows`` (an index array, or None for every arm)
    picks the arms a call concerns.
    """

    def __init__(self, n: int, n_muscles: int, params: FusimotorParams = SEED_PAPER) -> None:
        self.params = params
        keep = math.ceil(params.delay_s * params.predictor_rate_hz) + 2
        self._t = np.zeros((n, keep))
        self._p = np.zeros((n, keep, n_muscles))
        self._u = np.zeros((n, keep, n_muscles))
        self._integral = np.zeros((n, n_muscles))

    def reset(self, t_s: np.ndarray, length_L0: np.ndarray,
              rows: np.ndarray | None = None) -> np.ndarray:
        """Arms ``rows`` at rest at ``length_L0`` (r, m) at times ``t_s`` (r,); returns the
        templates (= the lengths)."""
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

    def update(self, t_s: np.ndarray, length_L0: np.ndarray,
               rows: np.ndarray | None = None) -> np.ndarray:
        """Feed arms ``rows`` their input lengths (r, m) at times ``t_s`` (r,), each
        non-decreasing; return their templates (r, m)."""
        rows = slice(None) if rows is None else rows
        dt = self.params.predictor_period_s
        kp, ki = self.params.predictor_kp_1_s, self.params.predictor_ki_1_s2
        t_k = self._t[rows, -1]
        due = t_s >= t_k + dt * (1.0 - 1e-9)
        if not due.any():
            return self._p[rows, -1] + self._u[rows, -1] * (t_s - t_k)[:, None]
        t_k = t_k.copy()
        p = self._p[rows, -1].copy()
        u = self._u[rows, -1].copy()
        integral = self._integral[rows]  # a copy for an index array, written back below
        arms = np.arange(self._t.shape[0])[rows]
        # A bridged gap takes several updates: each pass moves the arms still due by one.
        while True:
            i = np.flatnonzero(due)
            if i.size == 0:
                break
            # at a clock so large (beyond 2^48 s) that t_k + dt rounds to t_k, the next
            # representable time: every update moves on, so the loop ends
            t_new = np.maximum(t_k[i] + dt, np.nextafter(t_k[i], math.inf))
            p_new = p[i] + dt * u[i]
            error = length_L0[i] - p_new
            w = integral[i] + (ki * dt) * error
            u_new = kp * error + w
            integral[i], t_k[i], p[i], u[i] = w, t_new, p_new, u_new
            for array, new in ((self._t, t_new), (self._p, p_new), (self._u, u_new)):
                array[arms[i], :-1] = array[arms[i], 1:]
                array[arms[i], -1] = new
            due[i] = t_s[i] >= t_new + dt * (1.0 - 1e-9)
        self._integral[rows] = integral
        return p + u * (t_s - t_k)[:, None]

    def update_block(self, t_s: np.ndarray, length_L0: np.ndarray, given: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`update` of every arm with its inputs ``length_L0[i, j]`` (n, k, m) at times
        ``t_s[i, j]`` (n, k) for the columns j where ``given[i, j]`` (each arm's given
        columns first, times increasing), then :meth:`template_at` ``t_s - delay_s`` after
        each: returns (templates, delayed templates), each (n, k, m), the same numbers as
        those calls column by column (meaningless where not given).

        The PI updates run in rounds (one per update of the arm with most; a block of one
        env step holds one or two), the templates of all columns then in a few gathers."""
        n, k = t_s.shape
        keep = self._t.shape[1]
        dt = self.params.predictor_period_s
        kp, ki = self.params.predictor_kp_1_s, self.params.predictor_ki_1_s2
        times = np.where(given, t_s, -math.inf)
        t_k = self._t[:, -1].copy()
        p = self._p[:, -1].copy()
        u = self._u[:, -1].copy()
        integral = self._integral.copy()
        made = np.zeros(n, dtype=np.int64)
        rounds = []
        while True:
            due = times >= (t_k + dt * (1.0 - 1e-9))[:, None]
            i = np.flatnonzero(due.any(axis=1))
            if i.size == 0:
                break
            j = due[i].argmax(axis=1)  # the first column due: its input drives the update
            # (the next representable time at a clock beyond 2^48 s: see update)
            t_new = np.maximum(t_k[i] + dt, np.nextafter(t_k[i], math.inf))
            p_new = p[i] + dt * u[i]
            error = length_L0[i, j] - p_new
            w = integral[i] + (ki * dt) * error
            u_new = kp * error + w
            integral[i], t_k[i], p[i], u[i] = w, t_new, p_new, u_new
            rounds.append((i, j, made[i], t_new, p_new, u_new))
            made[i] += 1
        extra = int(made.max()) if rounds else 0
        width = keep + extra
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
        # template_at: the newest of the `keep` updates kept at that column with a time at
        # or before t - delay (else the oldest kept); the updates made at later columns lie
        # after t (they were not due at t), so the search may run over the whole row
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

    def template_at(self, t_s: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """The templates of arms ``rows`` at earlier times ``t_s`` (r,), each clamped to the
        arm's oldest kept update."""
        rows = slice(None) if rows is None else rows
        times = self._t[rows]
        # the newest update at or before t_s (times increase along a row); before the
        # oldest, the oldest's p: its u times a time clipped at 0 adds exactly nothing
        later = (times > t_s[:, None]).sum(axis=1)
        newest = np.maximum(times.shape[1] - 1 - later, 0)
        r = np.arange(times.shape[0])
        since = np.maximum(t_s - times[r, newest], 0.0)
        return self._p[rows][r, newest] + self._u[rows][r, newest] * since[:, None]

    def snapshot(self) -> tuple:
        """The predictors' state, for :meth:`restore` (a caller undoing a failed update)."""
        return tuple(a.copy() for a in (self._t, self._p, self._u, self._integral))

    def restore(self, snapshot: tuple) -> None:
        """Put back the state a :meth:`snapshot` of these predictors returned (once)."""
        self._t, self._p, self._u, self._integral = snapshot


class BatchedFusimotor:
    """:class:`Fusimotor` for ``n`` independent arms: (n, n_muscles) arrays.

    Args:
        n: number of arms.
        length_min_L0, length_max_L0: (n_muscles,) each muscle's range (shared by the arms).
        params: :class:`FusimotorParams`.
    """

    def __init__(self, n: int, length_min_L0: np.ndarray, length_max_L0: np.ndarray,
                 params: FusimotorParams = SEED_PAPER) -> None:
        self.length_min_L0 = np.array(length_min_L0, dtype=float, ndmin=1)
        self.length_max_L0 = np.array(length_max_L0, dtype=float, ndmin=1)
        if np.any(~(self.length_max_L0 > self.length_min_L0)):
            raise ValueError(
                f"length_max_L0={self.length_max_L0!r} must exceed length_min_L0="
                f"{self.length_min_L0!r}"
            )
        self.params = params
        self.predictor = BatchedMotionPredictor(n, self.length_min_L0.size, params)

    def reset(self, t_s: np.ndarray, length_L0: np.ndarray,
              rows: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """Arms ``rows`` at rest: (template_L0, gamma_static_pps, gamma_dynamic_pps)."""
        template = self.predictor.reset(t_s, length_L0, rows)
        return self._rates(t_s, template, rows)

    def update(self, t_s: np.ndarray, length_L0: np.ndarray,
               rows: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """Feed arms ``rows`` the template's input at ``t_s``; (template_L0, gamma_s,
        gamma_d), each (r, m)."""
        template = self.predictor.update(t_s, length_L0, rows)
        return self._rates(t_s, template, rows)

    def update_block(self, t_s: np.ndarray, length_L0: np.ndarray, given: np.ndarray
                     ) -> tuple[np.ndarray, ...]:
        """:meth:`update` over a block of columns (see
        :meth:`BatchedMotionPredictor.update_block`): (template_L0, gamma_s, gamma_d), each
        (n, k, m)."""
        template, delayed = self.predictor.update_block(t_s, length_L0, given)
        return (
            template,
            gamma_static_pps(template, self.length_min_L0, self.length_max_L0, self.params),
            gamma_dynamic_pps(template, delayed, self.params),
        )

    def _rates(self, t_s: np.ndarray, template: np.ndarray,
               rows: np.ndarray | None) -> tuple[np.ndarray, ...]:
        delayed = self.predictor.template_at(t_s - self.params.delay_s, rows)
        return (
            template,
            gamma_static_pps(template, self.length_min_L0, self.length_max_L0, self.params),
            gamma_dynamic_pps(template, delayed, self.params),
        )
