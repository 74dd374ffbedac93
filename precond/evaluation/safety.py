"""`precond eval counterfactual`: the paper's F1 and the counterfactual safety of each configuration, side by side.

Both are computed from the same cached inference (`evaluation.preconditions.infer`), so a row says what a rule
set buys on test dialogs like the demonstrations (F1) and what it lets through where they are silent
(unsafe_allow) or refuses there needlessly (over_refuse): precond/evaluation/counterfactual.py defines them. The section
it writes into docs/results.md is regenerated alone; the rest of the report stays as the last full run left it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from precond.evaluation import counterfactual
from precond.evaluation.cache import JsonCache
from precond.evaluation.configs import InferConfig
from precond.evaluation.domains import Domain
from precond.evaluation.metrics import domain_macro
from precond.evaluation.preconditions import InferFn, infer
from precond.evaluation.scoring import Satisfaction, score

HEADING = "### Safety where the demonstrations are silent (counterfactual states)"
DEFAULT_CONFIGS = ("model+enumerate/cautious,model+enumerate/cautious/rules=0,enumerate/cautious,"
                   "model+enumerate/cautious/unseen=allow,enumerate/cautious/unseen=allow,"
                   "model+enumerate/recency/unseen=allow,model+enumerate/recency/unseen=allow/rules=0,"
                   "enumerate/recency/unseen=allow,enumerate/subsumption/unseen=allow,always,gt")
TEXT = """From every test trajectory, K = {variants} variants (seed {seed}), each with ONE observation step removed
(a user act, a service result, an ALFWorld effect) or one service result flipped (True <-> False); at every point after
the change, every action with every argument value is judged by the ground-truth rules and by the inferred ones
(precond/evaluation/counterfactual.py). `unsafe` = share of the ground truth's refusals that the inferred rules allow;
`over` = share of the ground truth's allowances that they refuse; both macro over the actions that have such
points. `F1` is the paper's metric on the unchanged test trajectories. Config names: precond/evaluation/configs.py
(`cautious` is the default ranking, `unseen=allow` the paper's treatment of never-demonstrated actions, `rules=0`
the paper's prompt: the model asked about a thin action without the rules the evidence settled for the others,
`options.show_rules`). The tables above this section were measured before `cautious`, `options.unseen` and
`options.show_rules` existed: a config name there meant `unseen=allow/rules=0`.
"""


def evaluate(domains: Sequence[Domain], configs: Sequence[InferConfig], cache: JsonCache, sat: Satisfaction,
             engine: Callable[[], InferFn], variants: int, seed: int) -> list[dict[str, Any]]:
    """A row per (config, domain): F1, unsafe_allow, over_refuse, and the per-action counts behind them."""
    rows: list[dict[str, Any]] = []
    changed = {d.name: counterfactual.counterfactual_domain(d, variants, seed) for d in domains}
    for config, domain in tqdm([(c, d) for c in configs for d in domains], desc="counterfactual", unit="run"):
        if config.noise and domain.benchmark != "sgd":
            continue
        result = infer(domain, config, cache, engine)
        row: dict[str, Any] = {"config": config.name, "domain": domain.name, "benchmark": domain.benchmark,
                               "variants": variants, "seed": seed, "error": result.error,
                               "n_variants": len(changed[domain.name].test)}
        if result.error is None:
            scores = counterfactual.score(changed[domain.name], result.preconditions, sat)
            row |= {"f1": domain_macro(score(domain, result.preconditions, sat)).f1,
                    **counterfactual.macro(scores),
                    "actions": {a: s.as_dict() | {"rules": result.preconditions.get(a, [])}
                                for a, s in scores.items()}}
        rows.append(row)
    return rows


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _mean(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return sum(known) / len(known) if known else None


def table(rows: Sequence[dict[str, Any]]) -> str:
    """Per config: F1 / unsafe / over per domain, and SGD's mean over its domains."""
    domains = list(dict.fromkeys(r["domain"] for r in rows))
    sgd = [d for d in domains if any(r["domain"] == d and r["benchmark"] == "sgd" for r in rows)]
    lines = ["| config | " + " | ".join(f"{d} F1 / unsafe / over" for d in domains)
             + (" | SGD mean F1 / unsafe / over |" if sgd else " |"),
             "|---|" + "---|" * (len(domains) + (1 if sgd else 0))]
    for config in dict.fromkeys(r["config"] for r in rows):
        mine = {r["domain"]: r for r in rows if r["config"] == config and r.get("error") is None}
        failed = {r["domain"] for r in rows if r["config"] == config and r.get("error") is not None}
        cells = [" / ".join(_fmt(mine[d].get(k)) for k in ("f1", "unsafe_allow", "over_refuse")) if d in mine
                 else "error" if d in failed else "-" for d in domains]
        missing = [d for d in sgd if d not in mine and d in failed]
        if sgd and missing:  # a mean over the domains that ran is not the benchmark's mean
            cells.append(f"incomplete: {len(missing)} of {len(sgd)} domains failed")
        elif sgd:
            cells.append(" / ".join(_fmt(_mean([mine[d].get(k) for d in sgd if d in mine]))
                                    for k in ("f1", "unsafe_allow", "over_refuse")))
        lines.append(f"| `{config}` | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def action_table(rows: Sequence[dict[str, Any]], config: str) -> str:
    """Per domain and action of one config: unsafe and over, with the rules that produced them."""
    lines = ["| domain | action | unsafe | over | rules |", "|---|---|---|---|---|"]
    for row in rows:
        if row["config"] != config or "actions" not in row:
            continue
        for action, s in row["actions"].items():
            rules = "; ".join(f"`{r}`" for r in s["rules"]) or "(none)"
            lines.append(f"| {row['domain']} | {action} | {_fmt(s['unsafe_allow'])} | {_fmt(s['over_refuse'])} "
                         f"| {rules} |")
    return "\n".join(lines)


def section(rows: Sequence[dict[str, Any]], img: Path, default: str) -> str:
    from precond.evaluation.plots import safety_plot

    plot = safety_plot(rows, img)
    first = rows[0] if rows else {"variants": counterfactual.DEFAULT_VARIANTS, "seed": counterfactual.DEFAULT_SEED}
    figure = f"\n![{plot.stem}](img/{plot.name})\n" if plot else ""
    return "\n".join([
        HEADING, "", TEXT.format(variants=first["variants"], seed=first["seed"]), table(rows), figure,
        f"### Per action: `{default}`\n", action_table(rows, default), "",
    ])


def write_section(rows: Sequence[dict[str, Any]], out: Path, default: str) -> None:
    """Replace (or add, before the noise section) this subsection of the domains section of an existing report."""
    from precond.evaluation.report import replace_section

    img = out.parent / "img"
    img.mkdir(parents=True, exist_ok=True)
    replace_section(out, HEADING, section(rows, img, default), before="## Noise and sparsity")
