"""The noise and sparsity sweep's numbers (configs `noise`, precond/evaluation/configs.py): F1 per domain for strict and
tolerant validation, mean and spread over the seeds, for the report's table and plot."""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from precond.evaluation.configs import GRIDS, parse_config

ALL_DEMOS = 10


@dataclass(frozen=True)
class Setting:
    """One cell row of the sweep: how many demonstrations, what share of errors, which tolerance."""

    demos: int
    noise: float
    tolerance: float


@dataclass(frozen=True)
class Spread:
    mean: float
    sd: float
    seeds: int

    def __str__(self) -> str:
        return f"{self.mean:.3f} ± {self.sd:.3f}" if self.seeds > 1 else f"{self.mean:.3f}"


def setting(config: str) -> Setting | None:
    """The sweep setting a config name stands for; None for configs outside the sweep."""
    if config not in GRIDS["noise"]:
        return None
    parsed = parse_config(config)
    return Setting(parsed.demos or ALL_DEMOS, parsed.noise, float(parsed.options.get("tolerance", 0.0)))


def _spread(values: Sequence[float]) -> Spread:
    return Spread(statistics.fmean(values), statistics.pstdev(values) if len(values) > 1 else 0.0, len(values))


def collect(rows: Sequence[dict[str, Any]]) -> dict[Setting, dict[str, Spread]]:
    """Per setting, per SGD domain and for their mean ('mean': the domains' mean per seed, then over seeds)."""
    by_seed: dict[Setting, dict[str, dict[str, float]]] = {}
    for row in rows:
        found = setting(row["config"])
        if found is None or "macro" not in row or row["benchmark"] != "sgd":
            continue
        seed = row["config"].rsplit("sample=", 1)[-1] if "sample=" in row["config"] else "-"
        by_seed.setdefault(found, {}).setdefault(seed, {})[row["domain"]] = row["macro"]["f1"]
    out: dict[Setting, dict[str, Spread]] = {}
    for found, seeds in by_seed.items():
        domains = sorted({d for per in seeds.values() for d in per})
        cells = {d: _spread([per[d] for per in seeds.values() if d in per]) for d in domains}
        complete = [per for per in seeds.values() if len(per) == len(domains)]
        if complete:
            cells["mean"] = _spread([statistics.fmean(per.values()) for per in complete])
        out[found] = cells
    return out
