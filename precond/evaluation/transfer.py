"""`precond eval transfer`: prior rules across services, leave one domain out.

For each SGD dev domain, the priors are the default configuration's *inferred* rules of the other domains (one
source each; never their ground truth, never the held-out domain's test dialogs), and the held-out domain is
inferred with and without them. Both are scored by the paper's F1 on the test dialogs and by the
counterfactual metric (precond/evaluation/counterfactual.py), per domain and per action. A control transfers the
rules inferred for ALFWorld (another dialog vocabulary) to every SGD domain: they must change nothing.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from precond.evaluation import counterfactual
from precond.evaluation.cache import JsonCache
from precond.evaluation.configs import InferConfig
from precond.evaluation.domains import Domain
from precond.evaluation.metrics import domain_macro
from precond.evaluation.preconditions import Inference, InferFn, build_request, infer, run_request
from precond.evaluation.scoring import Satisfaction, score
from precond_client.schemas import PriorSource

HEADING = "## Prior rules from the tenant's other services (leave one domain out)"
TEXT = """Each SGD dev domain is inferred with the default configuration (`{config}`) twice: alone, and with priors =
the rules that configuration inferred for the other three domains (`options.prior_sources`, one vote each; their
inferred rules, never their ground truth). `F1` is the paper's metric on the test dialogs, `unsafe` / `over` the
counterfactual metric ({variants} variants per test dialog, seed {seed}). The ALFWorld control transfers ALFWorld's
inferred rules to every SGD domain (`alfworld = unchanged` when the rules are the same as without priors). What priors
add to an inference's time: `python bench/priors_bench.py` (priors never enter a prompt, so the model-free inference
is where their cost shows). Regenerate: `precond eval transfer`.
"""


def sources_for(held_out: Domain, domains: Sequence[Domain], config: InferConfig, cache: JsonCache,
                engine: Callable[[], InferFn]) -> list[PriorSource]:
    """The other domains' inferred rules, one source each (an inference that failed gives none)."""
    out = []
    for other in domains:
        if other.name == held_out.name:
            continue
        result = infer(other, config, cache, engine)
        if result.error is None:
            out.append(PriorSource(source=other.name, rules=result.preconditions))
    return out


def with_priors(domain: Domain, config: InferConfig, sources: Sequence[PriorSource], cache: JsonCache,
                engine: Callable[[], InferFn], force: bool = False) -> Inference:
    """The domain's inference with the priors, cached under the config and a digest of the priors."""
    digest = hashlib.sha256(json.dumps([s.model_dump() for s in sources], sort_keys=True).encode()).hexdigest()
    name = f"{config.name}+priors={digest[:16]}"
    stored = None if force else cache.get("infer", domain.infer_as, name)
    if stored is not None:
        return Inference(**stored)
    request = build_request(domain, config)
    options = request.options.model_copy(update={"prior_sources": list(sources)})
    result = run_request(engine(), request.model_copy(update={"options": options}))
    if result.error is None:
        cache.put(result.__dict__, "infer", domain.infer_as, name)
    return result


def _scored(domain: Domain, cf: Domain, result: Inference, sat: Satisfaction) -> dict[str, Any]:
    if result.error is not None:
        return {"error": result.error}
    paper = score(domain, result.preconditions, sat)
    safety = counterfactual.score(cf, result.preconditions, sat)
    return {"f1": domain_macro(paper).f1, **counterfactual.macro(safety), "wall_s": result.wall_s,
            "seconds": result.seconds,
            "actions": {a: {"f1": s.prf.f1 if s.prf else None, "unsafe_allow": safety[a].unsafe_allow,
                            "over_refuse": safety[a].over_refuse, "rules": result.preconditions.get(a, [])}
                        for a, s in paper.items()}}


def evaluate(sgd: Sequence[Domain], alfworld: Domain | None, config: InferConfig, cache: JsonCache,
             sat: Satisfaction, engine: Callable[[], InferFn], variants: int, seed: int, force: bool = False
             ) -> list[dict[str, Any]]:
    """A row per held-out SGD domain: without and with priors, the `always` baseline per action, the control."""
    rows = []
    control = infer(alfworld, config, cache, engine) if alfworld is not None else None
    for domain in sgd:
        cf = counterfactual.counterfactual_domain(domain, variants, seed)
        base = infer(domain, config, cache, engine, force)
        sources = sources_for(domain, sgd, config, cache, engine)
        transferred = with_priors(domain, config, sources, cache, engine, force)
        always = score(domain, {}, sat)
        row: dict[str, Any] = {"domain": domain.name, "config": config.name, "variants": variants, "seed": seed,
                               "sources": [s.source for s in sources],
                               "without": _scored(domain, cf, base, sat), "with": _scored(domain, cf, transferred, sat),
                               "always": {a: s.prf.f1 if s.prf else None for a, s in always.items()}}
        if control is not None and control.error is None:
            foreign = [PriorSource(source=alfworld.name if alfworld else "alfworld", rules=control.preconditions)]
            other = with_priors(domain, config, foreign, cache, engine, force)
            row["alfworld_unchanged"] = other.error is None and other.preconditions == base.preconditions
        rows.append(row)
    return rows


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def table(rows: Sequence[dict[str, Any]]) -> str:
    lines = ["| domain | without priors F1 / unsafe / over | with priors F1 / unsafe / over | alfworld |",
             "|---|---|---|---|"]
    keys = ("f1", "unsafe_allow", "over_refuse")
    means: dict[str, list[list[float]]] = {"without": [], "with": []}
    for row in rows:
        cells = []
        for side in ("without", "with"):
            found = row[side]
            cells.append(" / ".join(_fmt(found.get(k)) for k in keys) if "f1" in found else found.get("error", "-"))
            if "f1" in found:
                means[side].append([found[k] or 0.0 for k in keys])
        unchanged = {True: "unchanged", False: "CHANGED", None: "-"}[row.get("alfworld_unchanged")]
        lines.append(f"| {row['domain']} | {cells[0]} | {cells[1]} | {unchanged} |")
    mean = [" / ".join(_fmt(sum(v[k] for v in means[s]) / len(means[s])) for k in range(len(keys)))
            if means[s] else "-" for s in ("without", "with")]
    lines.append(f"| mean | {mean[0]} | {mean[1]} | |")
    return "\n".join(lines)


def action_table(rows: Sequence[dict[str, Any]]) -> str:
    """Per held-out domain and action: F1 (always's beside it) and the counterfactual metric, both ways."""
    lines = ["| domain | action | always F1 | F1 without / with | unsafe without / with | over without / with "
             "| rules with priors |", "|---|---|---|---|---|---|---|"]
    for row in rows:
        before, after = row["without"].get("actions", {}), row["with"].get("actions", {})
        for action, now in after.items():
            was = before.get(action, {})
            rules = "; ".join(f"`{r}`" for r in now["rules"]) or "(none)"
            pair = [f"{_fmt(was.get(k))} / {_fmt(now.get(k))}" for k in ("f1", "unsafe_allow", "over_refuse")]
            lines.append(f"| {row['domain']} | {action} | {_fmt(row['always'].get(action))} | "
                         + " | ".join(pair) + f" | {rules} |")
    return "\n".join(lines)


def section(rows: Sequence[dict[str, Any]]) -> str:
    first = rows[0] if rows else {"config": "-", "variants": counterfactual.DEFAULT_VARIANTS,
                                  "seed": counterfactual.DEFAULT_SEED}
    return "\n".join([HEADING, "", TEXT.format(config=first["config"], variants=first["variants"],
                                                seed=first["seed"]),
                      table(rows), "", "### Per action", "", action_table(rows), ""])


def write_section(rows: Sequence[dict[str, Any]], out: Path) -> None:
    """Replace (or append) this section of an existing report; the rest stays as it is."""
    text = out.read_text(encoding="utf-8") if out.exists() else ""
    start = text.find(HEADING)
    if start < 0:
        start = end = len(text)
    else:
        following = text.find("\n## ", start + len(HEADING))
        end = following + 1 if following >= 0 else len(text)
    out.write_text(text[:start] + section(rows) + "\n" + text[end:], encoding="utf-8")
