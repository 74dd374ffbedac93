"""`precond eval choose`: the learner's data-driven choices, picked by leave-one-domain-out on F1 within safety.

The paper's F1 is scored on test dialogs from the same generator as the demonstrations, where a rule that drops a
condition the dialogs never exercise loses nothing; the counterfactual metric (precond/evaluation/counterfactual.py)
scores the states where it matters. So a choice is taken on F1 only among the candidates that raise the unsafe
share on no development domain by more than its noise:

* a domain's reference is the candidate least unsafe there; a candidate *raises* unsafe on the domain when its
  share exceeds the reference's by more than `NOISE_SE` standard errors of the difference (`noise`);
* among the candidates that raise it nowhere, the highest mean F1 over the domains wins (ties: the one listed
  first, the one shipped before the procedure existed); where every candidate raises it somewhere, the one whose
  largest excess is least.

Leave-one-domain-out: each development domain's pick is made on the other domains alone and scored on it, so
the held-out figures say what the procedure gives a domain it never saw; the pick on all of them is what ships
(`CHOICES[...].shipped`, which the command checks).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

NOISE_SE = 2.0
"""How many standard errors of the difference an unsafe share may rise before it counts as raised."""


@dataclass(frozen=True)
class Choice:
    """One data-driven choice: its candidates as config suffixes (`""`: the base config as it is)."""

    name: str
    what: str
    candidates: Mapping[str, str]
    shipped: str


CHOICES: tuple[Choice, ...] = (
    Choice("signed notices", "what a failure notice, \"nothing found\" and \"not available\" need of the last result "
           "(precond/engine/candidates/library.py SIGNED; `empty`: an answer that is no success, also before "
           "anything was asked; `asked`: an answer came and it was no success)",
           {"empty": "notices=empty", "found-asked": "notices=found-asked",
            "found-asked-available": "notices=found-asked-available", "asked": "notices=asked",
            "empty-available": "notices=empty-available", "off": "notices=off"}, "found-asked-available"),
    Choice("answer slips", "`options.answer_slips`: the evidence weighting's bound on slips (0: a notice keeps "
           "'an answer came')", {"0.3": "", "0": "slips=0"}, "0.3"),
    Choice("tolerance", "`options.tolerance`: the share of an action's demonstrated calls a rule may miss and still "
           "hold (0: the paper's strict validation)", {"0.05": "", "0": "tol=0"}, "0.05"),
    Choice("unseen", "`options.unseen`: what a never-demonstrated guarded action gets when no prior and no guess "
           "decides it (`refuse`: the rule `False`; `allow`: no rule)", {"refuse": "", "allow": "unseen=allow"},
           "refuse"),
)


def config_name(base: str, suffix: str) -> str:
    return f"{base}/{suffix}" if suffix else base


def _macro_variance(row: Mapping[str, Any]) -> float:
    """Variance of a domain's macro unsafe share: binomial per action (add-one smoothed, so that 0 of n and n
    of n have a noise too), averaged over the actions that have refusals."""
    counts = [(s["unsafe"], s["refusals"]) for s in row.get("actions", {}).values() if s.get("refusals")]
    if not counts:
        return 0.0
    total = 0.0
    for unsafe, refusals in counts:
        p = (unsafe + 1) / (refusals + 2)
        total += p * (1 - p) / refusals
    return total / len(counts) ** 2


def noise(row: Mapping[str, Any], reference: Mapping[str, Any]) -> float:
    """How far a row's unsafe share may exceed the reference's on the same domain and count as noise."""
    return NOISE_SE * math.sqrt(_macro_variance(row) + _macro_variance(reference))


@dataclass(frozen=True)
class Raise:
    domain: str
    unsafe: float
    reference: str
    reference_unsafe: float
    noise: float

    def __str__(self) -> str:
        return (f"{self.domain} {self.reference_unsafe:.3f} ({self.reference}) -> {self.unsafe:.3f}, "
                f"noise {self.noise:.3f}")


Table = Mapping[str, Mapping[str, Mapping[str, Any]]]
"""candidate -> domain -> its `safety.evaluate` row."""


def raises(table: Table, candidate: str, domains: Sequence[str]) -> list[Raise]:
    """Each domain where the candidate's unsafe share exceeds the least unsafe candidate's beyond noise."""
    out = []
    for domain in domains:
        row = table[candidate][domain]
        reference = min(table, key=lambda c: table[c][domain]["unsafe_allow"] or 0.0)
        ref_row = table[reference][domain]
        mine, least = row["unsafe_allow"] or 0.0, ref_row["unsafe_allow"] or 0.0
        if mine - least > noise(row, ref_row):
            out.append(Raise(domain, mine, reference, least, noise(row, ref_row)))
    return out


def mean_f1(table: Table, candidate: str, domains: Sequence[str]) -> float:
    return sum(float(table[candidate][d]["f1"]) for d in domains) / len(domains)


def pick(table: Table, domains: Sequence[str]) -> str:
    """Max mean F1 among the candidates that raise unsafe nowhere in `domains`; if none, the least excess; with
    no domain to judge on, the first candidate."""
    if not domains:
        return next(iter(table))
    safe = [c for c in table if not raises(table, c, domains)]
    if safe:
        return max(safe, key=lambda c: (mean_f1(table, c, domains), -list(table).index(c)))

    def excess(c: str) -> float:
        return max(r.unsafe - r.reference_unsafe - r.noise for r in raises(table, c, domains))
    return min(table, key=excess)


def by_candidate(choice: Choice, base: str, rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """The evaluation's rows as candidate -> domain -> row (failed runs left out: `complete` says so)."""
    names = {config_name(base, suffix): label for label, suffix in choice.candidates.items()}
    table: dict[str, dict[str, Any]] = {label: {} for label in choice.candidates}
    for row in rows:
        if row["config"] in names and row.get("error") is None:
            table[names[row["config"]]][row["domain"]] = row
    return table


def complete(table: Table) -> list[str]:
    """The domains every candidate was scored on."""
    sets = [set(rows) for rows in table.values()]
    common = set.intersection(*sets) if sets else set()
    return [d for d in next(iter(table.values()), {}) if d in common]


@dataclass(frozen=True)
class Outcome:
    """A choice's pick on every domain, the pick each held-out domain got, and the table that says why."""

    picked: str
    held_out: dict[str, str]
    text: str = ""


def _cells(table: Table, candidate: str, domains: Sequence[str], held: Mapping[str, str]) -> list[str]:
    rows = [table[candidate][d] for d in domains]
    f1 = min(rows, key=lambda r: r["f1"])
    unsafe = max(rows, key=lambda r: r["unsafe_allow"] or 0.0)
    said = "; ".join(str(r) for r in raises(table, candidate, domains)) or "none"
    return [f"`{candidate}`", f"{mean_f1(table, candidate, domains):.3f}", f"{f1['f1']:.3f} ({f1['domain']})",
            f"{sum(r['unsafe_allow'] or 0.0 for r in rows) / len(rows):.3f}",
            f"{unsafe['unsafe_allow'] or 0.0:.3f} ({unsafe['domain']})",
            f"{sum(r['over_refuse'] or 0.0 for r in rows) / len(rows):.3f}", said,
            str(sum(1 for p in held.values() if p == candidate))]


def decide(choice: Choice, table: Table) -> Outcome:
    """The pick on all domains, each held-out domain's pick, and the table that says why."""
    domains = complete(table)
    held = {h: pick(table, [d for d in domains if d != h]) for h in domains}
    picked = pick(table, domains)
    lines = [f"### {choice.name}", "", choice.what, "",
             "| candidate | F1 mean | F1 worst | unsafe mean | unsafe worst | over mean | raises unsafe on "
             "(reference -> candidate, noise) | held-out domains picking it |", "|---|---|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(_cells(table, c, domains, held)) + " |" for c in table]
    scored = [table[p][h] for h, p in held.items()]
    worst = max(scored, key=lambda r: r["unsafe_allow"] or 0.0)
    why = ("the highest mean F1 of the candidates that raise unsafe on no domain" if not raises(table, picked, domains)
           else "every candidate raises unsafe somewhere: the least excess")
    lines += ["", f"Leave-one-domain-out ({len(domains)} domains, each scored with the pick of the others): F1 mean "
              f"{sum(r['f1'] for r in scored) / len(scored):.3f}, unsafe mean "
              f"{sum(r['unsafe_allow'] or 0.0 for r in scored) / len(scored):.3f}, worst "
              f"{worst['unsafe_allow'] or 0.0:.3f} ({worst['domain']}).",
              f"Picked on all {len(domains)} domains: `{picked}` ({why}); shipped: `{choice.shipped}`"
              + ("." if picked == choice.shipped else " (differs: ship the pick)."), ""]
    return Outcome(picked, held, "\n".join(lines))


def raised_against(rows: Sequence[Mapping[str, Any]], reference: str) -> list[str]:
    """Each (config, domain) whose unsafe share exceeds the reference config's on that domain beyond noise, in
    words (`precond eval domains --unsafe-against`); the baselines are no configurations to choose."""
    ref = {r["domain"]: r for r in rows if r["config"] == reference and r.get("error") is None}
    out = []
    for r in rows:
        base = ref.get(r["domain"])
        if r["config"] in (reference, "always", "gt") or r.get("error") is not None or base is None:
            continue
        mine, least = r.get("unsafe_allow") or 0.0, base.get("unsafe_allow") or 0.0
        if mine - least > noise(r, base):
            out.append(f"{r['config']} on {r['benchmark']} {r['domain']}: unsafe {mine:.3f} against {least:.3f} "
                       f"({reference}), noise {noise(r, base):.3f} (F1 {r.get('f1', 0.0):.3f})")
    return out
