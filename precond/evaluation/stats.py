"""Bootstrap confidence intervals, and paired differences between configurations on the same turns.

Turns of one dialog are not independent (one early mistake colours the rest of the dialog), so the unit that
is resampled is the dialog: each resample draws dialogs with replacement and takes the mean over all their
values (turns or predicted actions), the same ratio the point estimate is. A paired comparison draws the
same dialogs for both configurations, so what varies between dialogs cancels out of the difference.
Pure functions: seeded, no I/O.
"""

from __future__ import annotations

import random
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

RESAMPLES = 2000
LEVEL = 0.95


@dataclass(frozen=True)
class Interval:
    estimate: float
    low: float
    high: float
    n: int
    """How many values (turns, actions) the estimate is over."""

    def excludes_zero(self) -> bool:
        return self.low > 0 or self.high < 0


def _pooled(units: Sequence[Sequence[float]], picks: Sequence[int]) -> tuple[float, int]:
    total = sum(sum(units[i]) for i in picks)
    count = sum(len(units[i]) for i in picks)
    return total, count


def _quantiles(values: list[float], level: float) -> tuple[float, float]:
    values.sort()
    tail = (1 - level) / 2
    low = values[min(len(values) - 1, int(tail * len(values)))]
    high = values[min(len(values) - 1, int((1 - tail) * len(values)))]
    return low, high


def bootstrap(units: Sequence[Sequence[float]], resamples: int = RESAMPLES, level: float = LEVEL,
              seed: int = 0) -> Interval:
    """Mean over all values of all units, with a percentile interval from resampling whole units."""
    total, count = _pooled(units, range(len(units)))
    if count == 0:
        return Interval(0.0, 0.0, 0.0, 0)
    rng = random.Random(seed)
    means: list[float] = []
    for _ in range(resamples):
        s, c = _pooled(units, [rng.randrange(len(units)) for _ in units])
        if c:
            means.append(s / c)
    low, high = _quantiles(means, level)
    return Interval(total / count, low, high, count)


def paired_difference(a: Mapping[str, Sequence[float]], b: Mapping[str, Sequence[float]],
                      resamples: int = RESAMPLES, level: float = LEVEL, seed: int = 0) -> Interval:
    """mean(b) - mean(a) over the units both measured, each resample drawing the same units for both.

    Units are keyed (dialog ids); a unit only one side has is left out, so the two means are always taken
    over the same dialogs.
    """
    keys = sorted(set(a) & set(b))
    ua, ub = [a[k] for k in keys], [b[k] for k in keys]

    def diff(picks: Sequence[int]) -> float | None:
        (sa, ca), (sb, cb) = _pooled(ua, picks), _pooled(ub, picks)
        return sb / cb - sa / ca if ca and cb else None

    estimate = diff(range(len(keys)))
    if estimate is None:
        return Interval(0.0, 0.0, 0.0, 0)
    rng = random.Random(seed)
    diffs = [d for d in (diff([rng.randrange(len(keys)) for _ in keys]) for _ in range(resamples))
             if d is not None]
    low, high = _quantiles(diffs, level)
    return Interval(estimate, low, high, sum(len(u) for u in ub))
