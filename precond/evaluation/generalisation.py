"""`precond eval domains`: every development domain, each benchmark summed up so that a mean cannot hide a domain.

A mean over domains flatters a learner that is excellent on most services and useless on one: the one is what a
tenant with that kind of service gets. So each (config, benchmark) line gives, beside the mean, the worst domain
and how many domains score at or below `always` (no rule at all) on the paper's F1; the counterfactual metric
(precond/evaluation/counterfactual.py) likewise with its worst domain. Rows come from
`precond.evaluation.safety.evaluate`, so a config's inference is the cached one every other table reads.

Every config row says how it was chosen (`HOW_CHOSEN`): a shipped default fixed before these domains existed, a
baseline, or leave-one-domain-out (anything chosen from data is chosen without the domain it is scored on).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

HEADING = "## Twenty development domains: mean, worst domain, domains at or below `always`"
BENCHMARKS = ("sgd", "star", "alfworld")
DEFAULT_CONFIGS = "model+enumerate/cautious,enumerate/cautious,always,gt"
HOW_CHOSEN: dict[str, str] = {
    "always": "baseline: no rule",
    "gt": "baseline: the ground truth (checks the scoring)",
    "model+enumerate/cautious": "the learner before guarded actions and the rule library (main at bc4936d): its "
                                "criterion was fixed on 4 SGD services before the other 16 domains existed",
    "enumerate/cautious": "the same without the model",
    "model+enumerate/cautious/lib=lodo": "the library alone (every action guarded), each domain scored with the "
                                         "library of the others; measured before the thin failure-notice rule",
    "model+enumerate/cautious/guard=spec/lib=lodo": (
        "the shipped default (guarded actions from the spec, the rule library), each domain scored with the library "
        "of the others; `options.answer_slips` at its declared default 0.3 (the evidence weighting's bound on "
        "slips, fixed before measuring; leave-one-domain-out between 0 and 0.3 on mean F1 picks 0.3 for every "
        "domain: the `slips=0` rows); the learner's choices behind it (the priors' alternatives join a disjunction "
        "of triggers, a prior common at the calls replaces none of their rules, a yes covers what its party said "
        "before, a thin act keeps what it speaks of beside the priors) chosen by leave-one-domain-out among 7 "
        "variants (none, all, each left out alone) on the 20 development domains' mean F1 of the model-free row: "
        "every held-out domain chose all of them"),
    "enumerate/cautious/guard=spec/lib=lodo": (
        "the shipped default without the model: guarded actions from the spec (fixed before measuring), the rule "
        "library leave-one-domain-out (each domain scored with the `lib=0` rules of the other 20, never its own, "
        "never ground truth); its data-driven choices (the signed notices' readings, `options.answer_slips`) "
        "picked by `precond eval choose`: the highest mean F1 over the 21 development domains among the "
        "candidates that raise the counterfactual unsafe share on no domain beyond noise"),
    "model+enumerate/cautious/guard=spec/lib=lodo/slips=0": "the shipped default with `options.answer_slips` 0 (a "
                                                            "notice keeps 'an answer came'): the comparison for its "
                                                            "declared default 0.3",
}
TEXT = """Per benchmark (SGD: 14 services; STAR: 6 tasks of human agents; ALFWorld valid_unseen): the mean over its
domains, the worst domain, and `<=always` = how many domains score at or below `always` (no rule) on the paper's
F1. `unsafe` / `over`: the counterfactual metric ({variants} variants per test dialog, seed {seed}), mean and worst
domain. "how chosen" says where a row's settings come from: no rule a row's domain is scored with was inferred on it
(the library leaves it out), and the learner's data-driven choices were picked on all 21 domains within safety
(`precond eval choose` also prints the pick each held-out domain gets from the others). Regenerate: `precond eval
domains --configs "enumerate/cautious/guard=spec/lib=lodo,always,gt"` (model-free; cached inferences are reused).
"""


@dataclass(frozen=True)
class Summary:
    """One config on one benchmark."""

    config: str
    benchmark: str
    domains: int
    f1_mean: float
    f1_worst: tuple[str, float]
    at_or_below_always: list[str]
    unsafe_mean: float | None
    unsafe_worst: tuple[str, float] | None
    over_mean: float | None
    over_worst: tuple[str, float] | None


def _mean(values: Sequence[float]) -> float | None:
    return sum(values) / len(values) if values else None


def _worst(rows: Sequence[Mapping[str, Any]], key: str, highest: bool) -> tuple[str, float] | None:
    known = [(r["domain"], r[key]) for r in rows if r.get(key) is not None]
    if not known:
        return None
    return max(known, key=lambda x: x[1]) if highest else min(known, key=lambda x: x[1])


def summarize(rows: Sequence[Mapping[str, Any]]) -> list[Summary]:
    """Per (config, benchmark); a domain's `always` F1 comes from the `always` rows of the same run, and a config
    measured without them has no `<=always` count (an empty list would read as "none")."""
    scored = [r for r in rows if r.get("error") is None and r.get("f1") is not None]
    always = {r["domain"]: r["f1"] for r in scored if r["config"] == "always"}
    out = []
    for config in dict.fromkeys(r["config"] for r in scored):
        for benchmark in dict.fromkeys(r["benchmark"] for r in scored):
            mine = [r for r in scored if r["config"] == config and r["benchmark"] == benchmark]
            if not mine:
                continue
            worst = _worst(mine, "f1", highest=False)
            assert worst is not None
            below = [r["domain"] for r in mine if r["domain"] in always and r["f1"] <= always[r["domain"]] + 1e-9]
            unsafe = [r["unsafe_allow"] for r in mine if r.get("unsafe_allow") is not None]
            over = [r["over_refuse"] for r in mine if r.get("over_refuse") is not None]
            out.append(Summary(config, benchmark, len(mine), sum(r["f1"] for r in mine) / len(mine), worst, below,
                               _mean(unsafe), _worst(mine, "unsafe_allow", True), _mean(over),
                               _worst(mine, "over_refuse", True)))
    return out


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _fmt_worst(worst: tuple[str, float] | None) -> str:
    return "-" if worst is None else f"{worst[1]:.3f} ({worst[0]})"


PARTS = {
    "lib=lodo": "rule library leave-one-domain-out (each domain scored with the library of the other 20: their "
                "`lib=0` inferred rules, never its own, never ground truth)",
    "guard=spec": "`options.guarded` default from the spec (conversational acts by name), fixed before measuring",
    "slips=0": "`options.answer_slips` 0 (a notice keeps 'an answer came'): the comparison for its declared default",
}


def how_chosen(config: str, notes: Mapping[str, str] | None = None) -> str:
    """The row's own note, else what its base config and its `key=value` parts say."""
    if (notes or {}).get(config):
        return (notes or {})[config]
    if config in HOW_CHOSEN:
        return HOW_CHOSEN[config]
    parts = config.split("/")
    base = "/".join(p for p in parts if p not in PARTS)
    said = [HOW_CHOSEN.get(base, "a setting of the learner, not chosen from data")]
    return "; ".join([*said, *(PARTS[p] for p in parts if p in PARTS)])


def summary_table(summaries: Sequence[Summary], notes: Mapping[str, str] | None = None) -> str:
    lines = ["| benchmark | config | domains | F1 mean | F1 worst | <=always | unsafe mean | unsafe worst | over mean "
             "| over worst | how chosen |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    order = {b: i for i, b in enumerate(BENCHMARKS)}
    for s in sorted(summaries, key=lambda s: order.get(s.benchmark, len(order))):
        below = "-" if s.config == "always" else f"{len(s.at_or_below_always)}" + (
            f" ({', '.join(s.at_or_below_always)})" if s.at_or_below_always else "")
        lines.append(f"| {s.benchmark} | `{s.config}` | {s.domains} | {s.f1_mean:.3f} | {_fmt_worst(s.f1_worst)} | "
                     f"{below} | {_fmt(s.unsafe_mean)} | {_fmt_worst(s.unsafe_worst)} | {_fmt(s.over_mean)} | "
                     f"{_fmt_worst(s.over_worst)} | {how_chosen(s.config, notes)} |")
    return "\n".join(lines)


def domain_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """A row per domain, a column per config: F1 / unsafe / over."""
    configs = list(dict.fromkeys(r["config"] for r in rows))
    index = {(r["config"], r["domain"]): r for r in rows}
    lines = ["| benchmark | domain | " + " | ".join(f"`{c}` F1 / unsafe / over" for c in configs) + " |",
             "|---|---|" + "---|" * len(configs)]
    for domain, benchmark in dict.fromkeys((r["domain"], r["benchmark"]) for r in rows):
        cells = []
        for config in configs:
            row = index.get((config, domain))
            if row is None or row.get("error") is not None:
                cells.append(row.get("error", "-") if row else "-")
            else:
                cells.append(" / ".join(_fmt(row.get(k)) for k in ("f1", "unsafe_allow", "over_refuse")))
        lines.append(f"| {benchmark} | {domain} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def section(rows: Sequence[Mapping[str, Any]], notes: Mapping[str, str] | None = None, where: str = "") -> str:
    """`where`: the machine and time the section was written on (report.machine)."""
    first = rows[0] if rows else {"variants": "-", "seed": "-"}
    text = TEXT.format(variants=first["variants"], seed=first["seed"])
    return "\n".join([HEADING, "", text, *([where, ""] if where else []),
                      summary_table(summarize(rows), notes), "", "### Per domain", "", domain_table(rows), ""])


def write_section(rows: Sequence[Mapping[str, Any]], out: Path, notes: Mapping[str, str] | None = None) -> None:
    """This section first in the report; its counterfactual subsection (`precond eval counterfactual`) is kept."""
    import os

    from precond.evaluation.report import machine, replace_section
    from precond.evaluation.safety import HEADING as SAFETY

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    where = f"{machine()}\n- load average when written (1, 5, 15 min): {load}"
    replace_section(out, HEADING, section(rows, notes, where), before="## Noise and sparsity", stop=SAFETY)


def unsafe_breaches(rows: Sequence[Mapping[str, Any]], bound: float) -> list[str]:
    """Each (config, domain) whose counterfactual unsafe share exceeds `bound`, in words with its F1: a choice
    that raises the paper's F1 can drop a condition the test dialogs never exercise, so a configuration is
    judged by F1 only within this bound (`precond eval domains --max-unsafe`). The `always` and `gt` baselines
    are not configurations to choose."""
    out = []
    for r in rows:
        unsafe = r.get("unsafe_allow")
        if r["config"] in ("always", "gt") or r.get("error") is not None or unsafe is None or unsafe <= bound:
            continue
        f1 = r.get("f1")
        out.append(f"{r['config']} on {r['benchmark']} {r['domain']}: unsafe {unsafe:.3f} > {bound:.3f} "
                   f"(F1 {_fmt(f1)})")
    return out


MEASURES = (("over", "over_refuse", "over", "allows"), ("unsafe", "unsafe_allow", "unsafe", "refusals"))
"""(name, share, count, points) of each counterfactual measure in an action's row (`safety.evaluate`)."""


def costly_actions(rows: Sequence[Mapping[str, Any]], config: str, n: int) -> str:
    """Per benchmark, the `n` actions of `config` that refuse the largest share of what the ground truth allows in
    the counterfactual states and the `n` that allow the largest share of what it refuses, each with its domain,
    counts and rules: a benchmark's mean over-refusal is a mean over actions, so a few of them can make it, and
    their rules say why. Empty with `n` 0."""
    if n <= 0:
        return ""
    lines = ["| benchmark | measure | domain | action | share (count/points) | rules |", "|---|---|---|---|---|---|"]
    mine = [r for r in rows if r["config"] == config and r.get("error") is None]
    for benchmark in dict.fromkeys(r["benchmark"] for r in mine):
        scored = [(r["domain"], action, s) for r in mine if r["benchmark"] == benchmark
                  for action, s in r.get("actions", {}).items()]
        for name, share, count, points in MEASURES:
            costly = sorted((x for x in scored if x[2].get(count)), key=lambda x: -(x[2].get(share) or 0.0))[:n]
            for domain, action, s in costly:
                rules = "; ".join(f"`{r}`" for r in s.get("rules", [])) or "(none)"
                lines.append(f"| {benchmark} | {name} | {domain} | {action} | {_fmt(s.get(share))} "
                             f"({s[count]}/{s[points]}) | {rules} |")
    return "\n".join(lines)


def first_measured(rows: Sequence[Mapping[str, Any]]) -> str | None:
    """The first config of the rows that is not a baseline (`always`, `gt`)."""
    return next((r["config"] for r in rows if r["config"] not in ("always", "gt")), None)
