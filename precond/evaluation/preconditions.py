"""`precond eval preconditions`: infer on each domain's demonstrations, score on its test trajectories.

Inference goes through `Engine.infer`, exactly as a client's request would; the request carries the spec
and the demonstrations and nothing else (the domain's ground truth stays in `Domain.gt`). Each (domain,
configuration) inference is cached with its preconditions and phase timings, so scoring, tables and plots can
be regenerated without the model.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from tqdm import tqdm

from precond.evaluation.cache import JsonCache
from precond.evaluation.configs import InferConfig
from precond.evaluation.domains import Domain
from precond.evaluation.metrics import PRF, ActionScore, domain_macro, macro
from precond.evaluation.noise import corrupt, sample
from precond.evaluation.ranking_probe import rerank
from precond.evaluation.scoring import Satisfaction, score
from precond.sandbox import Sandbox
from precond_client.schemas import InferRequest, InferResponse
from precond_client.schemas.errors import PrecondError

InferFn = Callable[[InferRequest], InferResponse]


@dataclass(frozen=True)
class Inference:
    """What one inference produced, as cached: enough to score and to report timings, nothing more."""

    preconditions: dict[str, list[str]]
    seconds: dict[str, float]
    wall_s: float
    model: str | None
    error: str | None = None
    valid: dict[str, list[str]] = field(default_factory=dict)  # for re-ranking probes without the model


def demonstrations(domain: Domain, config: InferConfig) -> list[str]:
    """The request's demonstrations: the first N, or a seeded sample of N, with errors injected if asked."""
    demos = list(domain.demonstrations)
    if config.demos:
        demos = sample(demos, config.demos, config.sample) if config.sample is not None else demos[: config.demos]
    if config.noise:
        if domain.benchmark != "sgd":
            raise ValueError(f"{config.name}: errors are injected into SGD dialogs only, not {domain.name}")
        demos = corrupt(demos, config.noise, config.sample or 0)
    return demos


def build_request(domain: Domain, config: InferConfig) -> InferRequest:
    return InferRequest(spec=domain.spec, demonstrations=demonstrations(domain, config),
                        actions=list(domain.actions), options=config.infer_options(domain.actions))


def _run_engine(infer: InferFn, domain: Domain, config: InferConfig) -> Inference:
    return run_request(infer, build_request(domain, config))


def run_request(infer: InferFn, request: InferRequest) -> Inference:
    """One inference as the cache keeps it; an engine error is the result's `error`, not an exception."""
    start = time.perf_counter()
    try:
        response = infer(request)
    except PrecondError as exc:
        return Inference({}, {}, time.perf_counter() - start, None, f"{exc.kind}: {exc.message}")
    wall = time.perf_counter() - start
    model = response.model.name if response.model else None
    valid = {a: [c.assertion for c in reports if c.valid] for a, reports in response.candidates.items()}
    return Inference(response.preconditions, dict(response.stats.seconds), wall, model, valid=valid)


def infer(domain: Domain, config: InferConfig, cache: JsonCache, engine: Callable[[], InferFn],
          force: bool = False, sandbox: Sandbox | None = None) -> Inference:
    """Baselines need no engine; everything else is cached per (domain, config) unless `force`."""
    if config.baseline == "always":
        return Inference({}, {}, 0.0, None)
    if config.baseline == "gt":
        return Inference(dict(domain.gt), {}, 0.0, None)
    if config.max_rate is not None:
        return _probe(domain, config, cache, engine, sandbox)
    if config.library:
        return _held_out_library(domain, config, cache, engine, force)
    stored = None if force else cache.get("infer", domain.infer_as, config.name)
    if stored is not None:
        return Inference(**stored)
    result = _run_engine(engine(), domain, config)
    if result.error is None:  # errors (e.g. no model) are retried on the next run, not cached
        cache.put(result.__dict__, "infer", domain.infer_as, config.name)
    return result


def _held_out_library(domain: Domain, config: InferConfig, cache: JsonCache, engine: Callable[[], InferFn],
                      force: bool) -> Inference:
    """`lib=lodo`: inferred with the rule library of the other development domains (precond/evaluation/library.py),
    cached under a digest of that library."""
    from precond.evaluation import library

    pool = [d for d in library.development_domains() if d.infer_as != domain.infer_as]
    held = library.build(pool, config, cache, lambda d, c: infer(d, c, cache, engine))
    name = f"{config.name}+{library.digest(held)}"
    stored = None if force else cache.get("infer", domain.infer_as, name)
    if stored is not None:
        return Inference(**stored)
    result = run_request(library.with_library(engine(), held), build_request(domain, config))
    if result.error is None:
        cache.put(result.__dict__, "infer", domain.infer_as, name)
    return result


def _probe(domain: Domain, config: InferConfig, cache: JsonCache, engine: Callable[[], InferFn],
           sandbox: Sandbox | None) -> Inference:
    """Re-rank the base inference's valid candidates (precond/evaluation/ranking_probe.py); cheap, so not cached."""
    if sandbox is None:
        raise ValueError(f"{config.name}: a re-ranking probe needs the sandbox")
    base = infer(domain, config.base, cache, engine)
    if base.error is None and not base.valid:  # cached before candidates were kept: infer once more
        base = infer(domain, config.base, cache, engine, force=True)
    if base.error is not None:
        return base
    rate = config.max_rate or 1.0
    chosen = rerank(domain, demonstrations(domain, config), base.valid, sandbox, config.ranking, rate)
    return replace(base, preconditions=chosen)


def action_row(s: ActionScore) -> dict[str, Any]:
    prf = s.prf.as_dict() if s.prf else None
    return {"n_points": s.n_points, "n_pred": s.n_pred, "n_gt": s.n_gt, "n_both": s.n_both, "prf": prf}


def evaluate(domains: Sequence[Domain], configs: Sequence[InferConfig], cache: JsonCache, sat: Satisfaction,
             engine: Callable[[], InferFn], force: bool = False, sandbox: Sandbox | None = None
             ) -> dict[str, Any]:
    """Every config on every domain; a row per (config, domain) plus the benchmark-level macro per config."""
    rows: list[dict[str, Any]] = []
    # errors are injected into SGD dialogs only: a noise config has no ALFWorld row
    pairs = [(c, d) for c in configs for d in domains if not (c.noise and d.benchmark != "sgd")]
    for config, domain in tqdm(pairs, desc="preconditions", unit="run"):
        result = infer(domain, config, cache, engine, force, sandbox)
        row: dict[str, Any] = {"config": config.name, "domain": domain.name, "benchmark": domain.benchmark,
                               "uses_model": config.uses_model,
                               "n_demos": len(demonstrations(domain, config)),
                               "seconds": result.seconds, "wall_s": result.wall_s, "model": result.model,
                               "error": result.error, "preconditions": result.preconditions,
                               "valid_candidates": sum(len(v) for v in result.valid.values())}
        if result.error is None:
            scores = score(domain, result.preconditions, sat)
            row["macro"] = domain_macro(scores).as_dict()
            row["actions"] = {a: action_row(s) for a, s in scores.items()}
        rows.append(row)
    return {"rows": rows, "summary": summarize(rows)}


def summarize(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per config and benchmark: the mean of the domains' macros (see evaluation.metrics)."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["config"], row["benchmark"]), []).append(row)
    out = []
    for (config, benchmark), members in groups.items():
        scored = [PRF(**m["macro"]) for m in members if "macro" in m]
        out.append({"config": config, "benchmark": benchmark, "domains": len(scored),
                    "errors": sorted({m["error"] for m in members if m.get("error")}),
                    "macro": macro(scored).as_dict() if scored else None})
    return out
