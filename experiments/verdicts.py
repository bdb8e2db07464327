"""The statistics behind REPORT.md's verdicts: intervals that treat training seeds as a level of
their own, paired per-route differences, and the verdict rule.

A result of an experiment is a set of units (routes, frames) per training seed. The estimate is
the mean over seeds of each seed's mean over its units; its 95 % interval is a two-level
percentile bootstrap (Davison & Hinkley 1997, Sec. 3.8): seeds are resampled with replacement,
then units within each seed drawn, so that routes or frames of one seed never pass for
independent samples of the seed-to-seed variation. With one seed the interval covers the
routes (frames) only and holds for that training run alone (a single run is one sample).

Comparisons between variants are paired: every variant drives the same routes, so the unit is
the difference of DS on one route (for the same training seed index), and the interval is that
of the mean difference. Frames that follow each other (the weather swap) are resampled in
blocks. A claim is *supported* when its whole interval lies on its side of zero (of one, for a
ratio), *contradicted* when it lies wholly on the other side, *undecided* otherwise; with fewer
than two units it is undecided.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

N_BOOT = 4000
SEED = 0  # the bootstrap's own generator: the same tables give the same report


def hierarchical(
    units: Mapping[object, np.ndarray],
    stat: Callable[[np.ndarray], float] | None = None,
    n_boot: int = N_BOOT,
    block: int = 1,
    rng: np.random.Generator | None = None,
) -> tuple[float, float, float]:
    """(estimate, lo, hi) of `stat` over the mean unit (module docstring).

    Args:
        units: per seed, an (n,) or (n, k) array of per-unit values (n >= 1).
        stat: (k,) mean vector -> the statistic (default: its first element).
        block: units resampled in contiguous blocks of this many (1: independently).
    """
    stat = stat or (lambda m: float(np.ravel(m)[0]))
    groups = [np.asarray(v, dtype=np.float64).reshape(len(v), -1) for v in units.values()]
    if not groups or any(len(g) == 0 for g in groups):
        raise ValueError("every seed needs at least one unit")
    est = stat(np.mean([g.mean(0) for g in groups], axis=0))
    rng = rng or np.random.default_rng(SEED)
    draws = np.empty(n_boot)
    for b in range(n_boot):
        picks = rng.integers(len(groups), size=len(groups)) if len(groups) > 1 else [0]
        means = [_resample(groups[i], block, rng).mean(0) for i in picks]
        draws[b] = stat(np.mean(means, axis=0))
    lo, hi = np.percentile(draws, [2.5, 97.5])
    return float(est), float(lo), float(hi)


def _resample(g: np.ndarray, block: int, rng: np.random.Generator) -> np.ndarray:
    n = len(g)
    if block <= 1 or n <= block:
        return g[rng.integers(n, size=n)]
    starts = rng.integers(n - block + 1, size=-(-n // block))
    idx = (starts[:, None] + np.arange(block)[None]).ravel()[:n]
    return g[idx]


def paired_differences(
    a: Mapping[object, Mapping[str, float]], b: Mapping[object, Mapping[str, float]]
) -> dict[object, np.ndarray]:
    """Per seed both have, a[seed][route] - b[seed][route] over the routes both drove (sorted
    by route id); seeds with no common route are left out."""
    out = {}
    for seed in sorted(set(a) & set(b), key=str):
        common = sorted(set(a[seed]) & set(b[seed]))
        if common:
            out[seed] = np.array([a[seed][r] - b[seed][r] for r in common])
    return out


def enough(units: Mapping[object, np.ndarray]) -> bool:
    """At least two units in all (an interval needs a spread)."""
    return sum(len(v) for v in units.values()) >= 2


def verdict(lo: float, hi: float, enough_units: bool = True, against: float = 0.0) -> str:
    """ "supported" if the interval [lo, hi] lies wholly above `against`, "contradicted" if
    wholly below, else "undecided" (module docstring)."""
    if not enough_units:
        return "undecided (too few samples for an interval)"
    return "supported" if lo > against else "contradicted" if hi < against else "undecided"
