"""The rule library: rules learned on the development domains, shipped with the service as priors for new ones.

A service's ten demonstrations cannot show what a failure notice requires when no call failed, or that a
goodbye does not need the search to have succeeded. Services that share a dialog vocabulary share those
answers, so the rules the default configuration inferred on each development domain (never their ground
truth) ship in `data/rule_library.json`, one source per domain, and are priors by default for every request
whose spec shares a source's vocabulary (`applies`). They are candidates like a tenant's own priors
(`engine.priors`): each runs on the request's demonstrations, one the demonstrations refute is dropped, and a
kept one says `decided: transferred` with `library:<domain>` as its source. The tenant's own priors come on top:
where a request carries its own prior rules for an action, the library is silent about that action.

Beside the domains' rules it ships the *signed notices* (`SIGNED`): a failure notice ("Sorry, that failed") needs a
result that is no success, "nothing was found" and "not available" an answer that is no success, a success notice a
success, in every domain whose spec defines the result, demonstrated or not (`Library.signed`; the selection keeps
one unless the request's demonstrations refute it), whatever else the domain learned (a disjunction with the user's
thanks).

`options.library: "off"` leaves it out. The evaluation builds the library for a held-out domain without that
domain (precond/evaluation/library.py), so no score comes from rules that saw the domain they are scored on.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

LIBRARY_FILE = Path(__file__).parents[1] / "data" / "rule_library.json"
PREFIX = "library:"
MIN_SHARED_ACTIONS = 3
"""A source applies to a spec with at least this many action names in common with it (a dialog vocabulary:
REQUEST, GOODBYE, ANYTHING_ELSE...); rules naming what the spec does not define are dropped anyway."""
SIGNED_SOURCE = "notices"
SIGNED: dict[str, tuple[str, ...]] = {"FAIL": ("not self.query_success",),
                                      "NOTHING_FOUND": ("self.query_success is False",),
                                      "NOT_AVAILABLE": ("self.query_success is False",),
                                      "SUCCESS": ("self.query_success",), "CONFIRMED": ("self.query_success",)}
"""Notices tied to a result of their sign, by a word of the method's name (`NOTIFY_FAILURE`, `INFORM_BOOKING_FAILED`,
`INFORM_NOTHING_FOUND`, `INFORM_VENUE_NOT_AVAILABLE`; `NOTIFY_SUCCESS`, `INFORM_BOOKING_CONFIRMED`): applied to every
spec that defines them (`for_spec`). "Nothing found" and "not available" report an answer, so they need one (`is
False`: refused before any search); a failure notice needs no success. Chosen by `precond eval choose` (the
`signed notices` choice: the highest F1 among the readings that raise the counterfactual unsafe share on no
development domain)."""


@dataclass(frozen=True)
class LibrarySource:
    """One development domain's inferred rules, keyed by the action's method name (`REQUEST`, not `SYSTEM.REQUEST`),
    so that a spec whose agent class is named differently still meets them."""

    source: str
    rules: Mapping[str, Sequence[str]]


@dataclass(frozen=True)
class Library:
    sources: tuple[LibrarySource, ...] = field(default_factory=tuple)
    signed: Mapping[str, Sequence[str]] = field(default_factory=dict)

    def for_spec(self, actions: Sequence[str], own: Mapping[str, Sequence[str]] | None = None
                 ) -> list[tuple[str, dict[str, list[str]]]]:
        """(source, action -> rules) of every source that applies to these actions (qualified names), without
        the actions the request's own priors speak of."""
        by_method = {a.rsplit(".", 1)[-1]: a for a in actions}
        taken = {a for a, rules in (own or {}).items() if rules}
        out = []
        for src in self.sources:
            if not applies(src, by_method):
                continue
            rules = {by_method[m]: list(r) for m, r in src.rules.items()
                     if m in by_method and by_method[m] not in taken and r}
            if rules:
                out.append((PREFIX + src.source, rules))
        signed = {action: found for action in by_method.values() if action not in taken
                  and (found := self.signed_rules(action))}
        if signed:
            out.append((PREFIX + SIGNED_SOURCE, signed))
        return out

    def signed_rules(self, action: str) -> list[str]:
        """The signed notices' rules for an action whose method name holds one of their words."""
        name = action.rsplit(".", 1)[-1].upper()
        return list(dict.fromkeys(r for word, rules in self.signed.items() if word in name for r in rules))

    def without(self, name: str) -> Library:
        """The library with one domain's source left out (leave-one-domain-out)."""
        return Library(tuple(s for s in self.sources if s.source != name), self.signed)


def applies(source: LibrarySource, by_method: Mapping[str, str]) -> bool:
    return len(set(source.rules) & set(by_method)) >= MIN_SHARED_ACTIONS


def from_json(data: Mapping[str, object]) -> Library:
    raw = data.get("sources", [])
    if not isinstance(raw, list):
        raise ValueError("rule library: 'sources' must be a list")
    signed = data.get("signed", {})
    if not isinstance(signed, dict):
        raise ValueError("rule library: 'signed' must map actions to rules")
    return Library(tuple(LibrarySource(str(s["source"]), {str(a): [str(r) for r in rules]
                                                          for a, rules in s["rules"].items()})
                         for s in raw), {str(a): tuple(str(r) for r in rules) for a, rules in signed.items()})


def to_json(library: Library) -> dict[str, object]:
    return {"format_version": 1, "signed": {a: list(r) for a, r in library.signed.items()},
            "sources": [{"source": s.source, "rules": {a: list(r) for a, r in s.rules.items()}}
                        for s in library.sources]}


@cache
def shipped() -> Library:
    """The library in the package (empty when the file is absent: a checkout that never built one)."""
    if not LIBRARY_FILE.exists():
        return Library()
    return from_json(json.loads(LIBRARY_FILE.read_text(encoding="utf-8")))
