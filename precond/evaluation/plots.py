"""The report's PNGs (matplotlib, headless). Each returns its path, or None when nothing is cached for it."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

PER_ACTION = ("always", "enumerate/recency", "model+enumerate/recency")
_DEMOS = re.compile(r"/demos=(\d+)")


def per_action_plot(rows: Sequence[dict[str, Any]], img: Path) -> Path | None:
    """Per-action F1, one panel per domain, a bar per configuration."""
    domains = list(dict.fromkeys(r["domain"] for r in rows if "actions" in r))
    configs = [c for c in PER_ACTION if any(r["config"] == c for r in rows)]
    if not domains or not configs:
        return None
    fig, axes = plt.subplots(len(domains), 1, figsize=(10, 2.6 * len(domains)), squeeze=False)
    width = 0.8 / len(configs)
    for ax, domain in zip(axes[:, 0], domains, strict=True):
        index = {r["config"]: r for r in rows if r["domain"] == domain and "actions" in r}
        actions = list(next(iter(index.values()))["actions"])
        for k, config in enumerate(c for c in configs if c in index):
            f1 = [(index[config]["actions"][a]["prf"] or {}).get("f1", 0.0) for a in actions]
            ax.bar([i + k * width for i in range(len(actions))], f1, width, label=config)
        ax.set_xticks([i + width * (len(configs) - 1) / 2 for i in range(len(actions))],
                      [a.split(".", 1)[1] for a in actions], rotation=30, fontsize=7, ha="right")
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("F1")
        ax.set_title(domain, fontsize=9)
    axes[0, 0].legend(fontsize=7, ncols=len(configs))
    return _save(fig, img / "per_action_f1.png")


def demos_plot(rows: Sequence[dict[str, Any]], img: Path) -> Path | None:
    """Macro F1 against the number of demonstrations given to inference, per base config and benchmark."""
    series: dict[str, dict[int, list[float]]] = {}
    for row in rows:
        if "macro" not in row or row["config"] in ("always", "gt"):
            continue
        if row["domain"] == "alfworld-trajectory":
            continue
        base = _DEMOS.sub("", row["config"])
        line = series.setdefault(f"{base} ({row['benchmark']})", {})
        line.setdefault(row["n_demos"], []).append(row["macro"]["f1"])
    series = {k: v for k, v in series.items() if len(v) > 1}
    if not series:
        return None
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, points in sorted(series.items()):
        xs = sorted(points)
        ax.plot(xs, [sum(points[x]) / len(points[x]) for x in xs], marker="o", label=label)
    ax.set_xlabel("demonstrations given to inference")
    ax.set_ylabel("macro F1")
    ax.set_ylim(0, 1.0)
    ax.legend(fontsize=7)
    return _save(fig, img / "f1_vs_demos.png")


def noise_plot(rows: Sequence[dict[str, Any]], img: Path) -> Path | None:
    """Mean SGD F1 against injected errors (all demonstrations) and against demonstrations (clean), strict and
    tolerant validation, error bars = the spread over seeds."""
    from precond.evaluation.sweep import ALL_DEMOS, collect

    cells = {s: c["mean"] for s, c in collect(rows).items() if "mean" in c}
    if not cells:
        return None
    fig, (by_noise, by_demos) = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for tolerance in sorted({s.tolerance for s in cells}):
        label = "strict (tolerance 0)" if tolerance == 0 else f"tolerance {tolerance:g}"
        noisy = sorted((s.noise, c) for s, c in cells.items() if s.tolerance == tolerance and s.demos == ALL_DEMOS)
        sparse = sorted((s.demos, c) for s, c in cells.items() if s.tolerance == tolerance and s.noise == 0)
        for ax, series in ((by_noise, noisy), (by_demos, sparse)):
            ax.errorbar([x for x, _ in series], [c.mean for _, c in series], yerr=[c.sd for _, c in series],
                        marker="o", capsize=3, label=label)
    by_noise.set_xlabel(f"share of system steps with an injected error ({ALL_DEMOS} demonstrations)")
    by_demos.set_xlabel("demonstrations (clean, drawn at random)")
    by_noise.set_ylabel("mean SGD macro F1")
    by_noise.legend(fontsize=8)
    return _save(fig, img / "noise_and_sparsity.png")


def sized_plot(rows: Sequence[dict[str, Any]], img: Path) -> Path | None:
    """Turn F1 and GT compatibility per configuration of the sized run, with their 95% intervals."""
    if not rows:
        return None
    fig, ax = plt.subplots(figsize=(8, 4))
    xs = range(len(rows))
    for offset, key, label in ((-0.2, "compatibility", "GT compatibility"), (0.2, "f1", "turn F1")):
        values = [r[key]["estimate"] for r in rows]
        errors = [[v - r[key]["low"] for v, r in zip(values, rows, strict=True)],
                  [r[key]["high"] - v for v, r in zip(values, rows, strict=True)]]
        ax.bar([x + offset for x in xs], values, 0.4, yerr=errors, capsize=4, label=label)
    ax.set_xticks(list(xs), [r["config"] for r in rows], rotation=15, ha="right", fontsize=8)
    ax.set_ylim(0, 1.05)
    ax.set_title(f"next action, {rows[0]['turns']} SGD turns per configuration (95% bootstrap intervals)", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    return _save(fig, img / "next_action_modes.png")


def _weighted(rows: Sequence[dict[str, Any]], config: str, key: str, weight: str) -> float:
    members = [r for r in rows if r["config"] == config]
    total = sum(r[weight] for r in members)
    return sum(r[key] * r[weight] for r in members) / total if total else 0.0


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def safety_plot(rows: Sequence[dict[str, Any]], img: Path) -> Path | None:
    """Counterfactual unsafe_allow against over_refuse per configuration, one point per domain (the paper's F1
    in the label's mean): the lower left corner is where a guard should be."""
    scored = [r for r in rows if r.get("unsafe_allow") is not None and r.get("over_refuse") is not None]
    if not scored:
        return None
    fig, ax = plt.subplots(figsize=(8, 5))
    markers = "os^vD<>Pp*"
    for k, config in enumerate(dict.fromkeys(r["config"] for r in scored)):
        mine = [r for r in scored if r["config"] == config]
        f1 = sum(r["f1"] for r in mine) / len(mine)
        ax.scatter([r["over_refuse"] for r in mine], [r["unsafe_allow"] for r in mine], label=f"{config} (F1 {f1:.2f})",
                   marker=markers[k % len(markers)], s=90 - 6 * k, alpha=0.75)
    ax.set_xlabel("over_refuse (share of the truth's allowances refused)")
    ax.set_ylabel("unsafe_allow (share of the truth's refusals allowed)")
    ax.set_xlim(-0.02, 1.02)
    ax.set_ylim(-0.02, 1.02)
    ax.legend(fontsize=7)
    ax.set_title("Counterfactual states: one point per domain")
    return _save(fig, img / "counterfactual_safety.png")
