"""The coefficients of the C tendon organ's log1p polynomial (``gto_log1p`` in
``spindle/native/c/tendon_organ.c``), printed as C.

``gto_log1p`` reduces ln(1 + x) to ln m, m in [sqrt(1/2), sqrt 2), and takes
ln m = f - f^2/2 + s (f^2/2 + w Q(w)) with f = m - 1, s = f / (2 + f), w = s^2, where
Q(w) = 2 (atanh(s)/s - 1) / w = sum_{j>=0} 2 w^j / (2j + 3) (so 2 atanh s = 2 s + s w Q(w)).
Q is replaced by its interpolant at the Chebyshev points of [0, W], W = ((sqrt 2 - 1) /
(sqrt 2 + 1))^2 (the largest w), of degree ``--degree`` (6: seven coefficients), computed in
200-bit arithmetic (mpmath) and rounded to double. Printed: ln 2 split into a 42-bit
head (so that k ln2_hi is exact for every exponent k) and the rest, the coefficients (of w^0
first) as C, and the largest error of the rounded polynomial on [0, W] as a share of ln m (the error
of s w Q against ln m ~ 2 s: w/2 times the error in Q; one ulp is 1.1e-16 to 2.2e-16).

Usage: ``python scripts/fit_log1p.py [--degree 6]``
"""

from __future__ import annotations

import argparse

import mpmath


def q_exact(w: mpmath.mpf) -> mpmath.mpf:
    if w == 0:
        return mpmath.mpf(2) / 3
    s = mpmath.sqrt(w)
    return 2 * (mpmath.atanh(s) / s - 1) / w


def chebyshev_fit(degree: int, W: mpmath.mpf) -> list[mpmath.mpf]:
    """Monomial coefficients (c0 first) of the interpolant of Q at degree + 1 Chebyshev
    points of [0, W]."""
    n = degree + 1
    nodes = [W / 2 * (1 - mpmath.cos((2 * i + 1) * mpmath.pi / (2 * n))) for i in range(n)]
    V = mpmath.matrix([[x ** j for j in range(n)] for x in nodes])
    return list(mpmath.lu_solve(V, mpmath.matrix([q_exact(x) for x in nodes])))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--degree", type=int, default=6)
    args = p.parse_args(argv)
    mpmath.mp.prec = 200
    W = ((mpmath.sqrt(2) - 1) / (mpmath.sqrt(2) + 1)) ** 2
    coefficients = [float(c) for c in chebyshev_fit(args.degree, W)]
    worst = mpmath.mpf(0)
    for i in range(2001):
        w = W * i / 2000
        approx = sum(mpmath.mpf(c) * w ** j for j, c in enumerate(coefficients))
        worst = max(worst, abs(approx - q_exact(w)) * w / 2)
    ln2 = mpmath.log(2)
    ln2_hi = float(mpmath.nint(ln2 * 2**42) / 2**42)  # k ln2_hi exact for |k| < 2^11
    print(f"#define GTO_LN2_HI {ln2_hi.hex()}")
    print(f"#define GTO_LN2_LO {float(ln2 - ln2_hi).hex()}")
    for j, c in enumerate(coefficients):
        print(f"#define GTO_LOG_Q{j} {c.hex()} /* {c!r} */")
    print(f"largest error of the rounded interpolant's share of ln m: "
          f"{float(worst):.3g} (2^{float(mpmath.log(worst, 2)):.1f})")


if __name__ == "__main__":
    main()
