"""Statistics for success rates."""

from __future__ import annotations

import math

Z_95 = 1.959963984540054


def wilson_interval(successes: int, trials: int, *, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (95% by default); (0, 1) for no trials."""
    if trials < 0 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials, got {successes}/{trials}")
    if trials == 0:
        return 0.0, 1.0
    p = successes / trials
    denominator = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denominator
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


def mcnemar_exact_p(b: int, c: int) -> float:
    """Two-sided p-value of McNemar's exact test on discordant counts `b` and `c`.

    p = min(1, 2·P(X ≤ min(b, c))) with X ~ Binomial(b + c, ½); 1 when b + c = 0. The tail is
    summed in integers and divided once, so the float is the exact value correctly rounded.
    """
    if b < 0 or c < 0:
        raise ValueError(f"need non-negative discordant counts, got b={b}, c={c}")
    n, k = b + c, min(b, c)
    if 2 * k >= n - 1:  # the smaller tail holds half the mass or more: p is 1
        return 1.0
    term = tail = 1  # C(n, 0)
    for i in range(k):
        term = term * (n - i) // (i + 1)  # C(n, i + 1), exact
        tail += term
    return min(1.0, tail / (1 << (n - 1)))
