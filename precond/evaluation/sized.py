"""`precond eval next-action`: the policy configurations on a seeded sample of SGD turns, with intervals.

Which turns: per domain, the test dialogs in a seeded random order, taken whole until at least `turns` system
turns are in (whole dialogs, because a turn's history is its dialog and because the dialog is the bootstrap's
unit, precond/evaluation/stats.py). Every configuration runs on exactly the same turns, dialog by dialog and
configuration by configuration, so results are paired at any moment: an interrupted run has the same turns
for every configuration, and continues from the per-turn cache (precond/evaluation/cache.py) where it stopped.
The progress bar counts segments (requests) over all domains and configurations and shows the ETA.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from tqdm import tqdm

from precond.evaluation.cache import JsonCache
from precond.evaluation.domains import Domain
from precond.evaluation.metrics import percentile, turn_f1
from precond.evaluation.policy import PolicyConfig, PolicyEngine, run_policy, segments
from precond.evaluation.stats import Interval, bootstrap, paired_difference


def sample_dialogs(dialogs: Sequence[dict[str, Any]], turns: int, seed: int) -> list[dict[str, Any]]:
    """Dialogs in a seeded order, whole, until their system turns reach `turns` (all of them if fewer)."""
    order = list(dialogs)
    random.Random(seed).shuffle(order)
    chosen: list[dict[str, Any]] = []
    count = 0
    for dialog in order:
        if count >= turns:
            break
        chosen.append(dialog)
        count += sum(1 for t in dialog["turns"] if t["speaker"] == "SYSTEM" and t["steps"][1] > t["steps"][0])
    return chosen


@dataclass(frozen=True)
class Task:
    domain: Domain
    dialogs: list[dict[str, Any]]
    preconditions: dict[str, list[str]]


def finished(cache: JsonCache, task: Task, dialog: dict[str, Any], configs: Sequence[PolicyConfig]) -> bool:
    """Every configuration has every segment of the dialog in the cache."""
    keys = {s.key for s in segments(dialog)}
    return all(keys <= set(cache.get("policy", task.domain.name, c.name, dialog["dialogue_id"]) or {})
               for c in configs)


EngineFor = Callable[[Task, PolicyConfig], PolicyEngine]


def run(engine_for: EngineFor, tasks: Sequence[Task], configs: Sequence[PolicyConfig], cache: JsonCache,
        seed: int = 0, replayed: Callable[[], float] | None = None, cached_only: bool = False
        ) -> dict[str, list[dict[str, Any]]]:
    """Per-segment results per configuration (keyed `config`), every configuration on the same dialogs;
    `engine_for` gives the engine of a domain's configuration (a BC row's model is fine-tuned per domain).

    `cached_only`: predict nothing; take the dialogs every configuration has finished (an interrupted run's
    results so far, still paired)."""
    chosen = [(t, d) for t, d in _rounds(tasks) if not cached_only or finished(cache, t, d, configs)]
    total = sum(len(list(segments(d))) for _, d in chosen) * len(configs)
    out: dict[str, list[dict[str, Any]]] = {c.name: [] for c in configs}
    with tqdm(total=total, unit="request", desc="next-action", smoothing=0.05) as bar:
        for task, dialog in chosen:
            for config in configs:
                pre = task.domain.gt if config.source == "gt" else task.preconditions
                rows = run_policy(engine_for(task, config), task.domain, config, pre, [dialog], cache, None, seed,
                                  replayed or (lambda: 0.0), lambda: None)
                bar.update(len(rows))
                bar.set_postfix_str(f"{task.domain.name} {config.name}")
                out[config.name] += [r | {"domain": task.domain.name} for r in rows]
    return out


def _rounds(tasks: Sequence[Task]) -> list[tuple[Task, dict[str, Any]]]:
    """One dialog of each domain in turn: a run stopped early still has every domain in it."""
    longest = max((len(t.dialogs) for t in tasks), default=0)
    return [(t, t.dialogs[k]) for k in range(longest) for t in tasks if k < len(t.dialogs)]


def units(results: Sequence[dict[str, Any]]) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Per dialog: the turn F1 of each of its turns (segments merged), and 1/0 per predicted action (GT allows)."""
    turns: dict[tuple[str, int], tuple[list[str], list[str]]] = {}
    compat: dict[str, list[float]] = {}
    for r in results:
        predicted, reference = turns.setdefault((r["dialog"], r["turn"]), ([], []))
        predicted.extend(r["predicted"])
        reference.extend(r["reference"])
        compat.setdefault(r["dialog"], []).extend(1.0 if c else 0.0 for c in r["compatible"])
    f1: dict[str, list[float]] = {}
    for (dialog, _), (predicted, reference) in turns.items():
        f1.setdefault(dialog, []).append(turn_f1(predicted, reference).f1)
    return f1, compat


def _interval(i: Interval) -> dict[str, float]:
    return {"estimate": i.estimate, "low": i.low, "high": i.high, "n": i.n}


def summarize(results: dict[str, list[dict[str, Any]]], baseline: str) -> list[dict[str, Any]]:
    """Per configuration: turn F1 and GT compatibility with 95% intervals, latency, and the paired
    difference to `baseline` on the same dialogs."""
    per = {name: units(rows) for name, rows in results.items()}
    rows = []
    for name, found in results.items():
        f1, compat = per[name]
        latency = [r["seconds"] for r in found]
        row: dict[str, Any] = {
            "config": name, "dialogs": len(f1), "turns": sum(map(len, f1.values())), "requests": len(found),
            "domains": sorted({r["domain"] for r in found}),
            "f1": _interval(bootstrap(list(f1.values()))),
            "compatibility": _interval(bootstrap(list(compat.values()))),
            "latency_p50_s": percentile(latency, 50), "latency_p95_s": percentile(latency, 95),
            "refused": sum(1 for r in found if r.get("error")),
            "nothing_allowed": sum(r.get("nothing_allowed", 0) for r in found),
        }
        if baseline in per and name != baseline:
            row["vs"] = baseline
            row["f1_diff"] = _interval(paired_difference(per[baseline][0], f1))
            row["compatibility_diff"] = _interval(paired_difference(per[baseline][1], compat))
        rows.append(row)
    return rows
