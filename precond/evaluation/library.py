"""The rule library on the development domains: what ships, and what each held-out domain is scored with.

The shipped library (`precond/engine/data/rule_library.json`, engine.library) holds, per development domain, the
rules the default configuration inferred there without any library (`lib=0`): inferred rules, never the
ground truth. Scoring a development domain with that library would let its own rules vote for themselves, so a
config with `lib=lodo` is inferred with the library of the *other* domains (leave one domain out); its cache key
carries a digest of that library, so a changed source re-runs the domain.

`precond eval library` writes the shipped file from the same cached inferences.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import cache
from pathlib import Path
from typing import Any

from precond.engine.candidates.library import LIBRARY_FILE, SIGNED, Library, LibrarySource, to_json
from precond.evaluation.cache import JsonCache
from precond.evaluation.configs import NOTICE_READINGS, InferConfig, parse_config
from precond.evaluation.domains import Domain

InferFn = Callable[[Any], Any]
BENCHMARK_DIRS = ("sgd", "star", "alfworld")


def source_config(config: InferConfig) -> InferConfig:
    """The same configuration without the library: what a source's rules are inferred with."""
    name = "/".join(p for p in config.name.split("/") if not p.startswith(("lib=", "notices=")))
    return parse_config(name)


@cache
def development_domains() -> tuple[Domain, ...]:
    """Every development domain under the data directory (an absent benchmark directory contributes none)."""
    from precond.evaluation.domains import load_domains
    from precond.evaluation.settings import DataSettings

    root = DataSettings().root
    found: list[Domain] = []
    for name in BENCHMARK_DIRS:
        if (root / name).is_dir():
            found.extend(load_domains(root / name))
    return tuple(found)


def source_of(domain: Domain, rules: dict[str, list[str]]) -> LibrarySource:
    """A domain's rules keyed by method name (`SYSTEM.REQUEST` -> `REQUEST`)."""
    return LibrarySource(domain.name, {a.rsplit(".", 1)[-1]: list(r) for a, r in rules.items() if r})


def build(domains: Sequence[Domain], config: InferConfig, cache_: JsonCache,
          infer_one: Callable[[Domain, InferConfig], Any]) -> Library:
    """One source per domain: its `lib=0` inference (one that failed gives none), and the config's signed
    notices (`notices=`; the shipped ones by default)."""
    plain = source_config(config)
    sources = []
    for domain in domains:
        result = infer_one(domain, plain)
        if result.error is None:
            sources.append(source_of(domain, result.preconditions))
    signed = NOTICE_READINGS[config.notices] if config.notices else SIGNED
    return Library(tuple(sources), dict(signed))


def held_out(library: Library, domain: Domain) -> Library:
    return library.without(domain.name)


def digest(library: Library) -> str:
    return hashlib.sha256(json.dumps(to_json(library), sort_keys=True).encode()).hexdigest()[:16]


def with_library(infer: InferFn, library: Library) -> InferFn:
    """The engine's infer with `library` as its rule library (the engine behind a bound `Engine.infer`)."""
    owner = getattr(infer, "__self__", None)
    if owner is None or not hasattr(owner, "library"):
        raise ValueError("lib=lodo needs the engine itself (Engine.infer), to give it the held-out library")

    def run(request: Any) -> Any:
        before = owner.library
        owner.library = library
        try:
            return infer(request)
        finally:
            owner.library = before

    return run


def write_shipped(library: Library, out: Path = LIBRARY_FILE) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(to_json(library), indent=1, sort_keys=True) + "\n", encoding="utf-8")
    return out


def lodo_note(config: InferConfig) -> str:
    return (f"rule library leave-one-domain-out: for each domain, the `{source_config(config).name}` rules of the "
            "other development domains (never its own, never ground truth)")


def without_library(config: InferConfig) -> InferConfig:
    return replace(config, options={k: v for k, v in config.options.items() if k != "library"})
