"""The gateway's own judgement of a check (`interpreted`, the restricted interpreter) against the worker's
(`Engine.check` with the real sandbox), on SGD domains: what tests/service/test_interpreted_differential*.py and
bench/interpreted_differential_bench.py compare. Every field must be equal but `judged_by`; a check the
interpreter cannot take (`offload.Queued`) is a difference too, so a shape the recogniser stops accepting is
found."""

from __future__ import annotations

import json
import random
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from precond.engine.engine import Engine
from precond.engine.scope import scoped
from precond.gateway import offload
from precond.store.sets import decided
from precond_client.schemas import CheckRequest, InferOptions, InferRequest, InferResponse

TAG = "differential"
HAND = {"SYSTEM.INFORM": ["slot in self.user.requested_slot", "self.user.requested_slot[slot] and slot not in "
                          "self.user.informed_slot", "self.query_success > 0",  # raises TypeError before a query
                          "self.user.informed_slot[slot] == self.user.informed_slot['date']"],
        "SYSTEM.REQUEST": ["not self.user.informed_slot[slot]", "slot not in self.user.informed_slot",
                           "len(slot) > 3 and slot in self.user.requested_slot"],
        "SYSTEM.GOODBYE": ["self.user.no_more or self.query_success is False"]}
CHUNK = 32


class Differs(AssertionError):
    """The interpreter and the sandbox answered a check differently (or the interpreter could not take it)."""


def judged_by_sandbox(engine: Engine, body: dict[str, Any]) -> dict[str, Any]:
    """The worker's answer: the engine's check, rules and history run in the sandbox."""
    with scoped(TAG):
        return engine.check(CheckRequest.model_validate(body)).model_dump(mode="json")


def judged_here(body: dict[str, Any]) -> dict[str, Any]:
    """The gateway's answer, as `/check-actions` screens a check before it would queue it."""
    outcome = offload.screened_check(body["spec"], body["preconditions"], body.get("decided", {}), body["history"],
                                     body["calls"], TAG, 1_000_000)
    if not isinstance(outcome, offload.Judged):
        raise Differs(f"not judged by the interpreter: {body['preconditions']}, {outcome}")
    return dict(outcome.answer)


def compare(engine: Engine, body: dict[str, Any], seen: Counter[str]) -> None:
    fast, slow = judged_here(body), judged_by_sandbox(engine, body)
    if (fast.pop("judged_by"), slow.pop("judged_by")) != ("interpreter", "sandbox") or fast != slow:
        raise Differs(body["preconditions"], body["history"][-300:] if isinstance(body["history"], str) else
                      len(body["history"]), body["calls"], fast, slow)
    for verdict in fast["results"]:
        seen.update(k for k, field in (("allowed", "allowed"), ("refused", "violations"), ("raised", "error"),
                                       ("labelled", "decided")) if verdict[field])
    seen.update(["history broken"] if fast["history_violation"] else [])


def labels(learned: InferResponse) -> dict[str, dict[str, str]]:
    """How each learned rule was decided, as a stored set labels it."""
    return decided(learned.preconditions, learned.evidence, learned.candidates)


def sgd_rule_sets(engine: Engine, domain: dict[str, Any]) -> list[tuple[dict[str, list[str]], dict[str, Any]]]:
    """Every enumerated condition (chunks of 32 an action), the learned rules with their labels, the hand ones.
    One inference gives both: `candidates: all` lists every proposal and leaves the rules as they are."""
    demos = [d["program"] for d in domain["demos"]]
    with scoped(TAG):
        learned = engine.infer(InferRequest(spec=domain["spec_program"], demonstrations=demos,
                                            options=InferOptions(generators=["enumerate"], candidates="all")))
    atoms = {a: list(dict.fromkeys(c.assertion for c in reports)) for a, reports in learned.candidates.items()}
    chunks = [{a: rules[k: k + CHUNK] for a, rules in atoms.items() if rules[k: k + CHUNK]}
              for k in range(0, max(len(r) for r in atoms.values()), CHUNK)]
    return [(chunk, {}) for chunk in chunks] + [(learned.preconditions, labels(learned)), (HAND, {})]


def sgd_checks(domain: dict[str, Any], dialogs: int) -> Iterator[tuple[str, list[str]]]:
    """(history, calls): every prefix of a dialog that ends before a system call, with every distinct system
    call of the domain's dialogs (a stub's) as the calls."""
    programs = [d["program"] for d in [*domain["test"], *domain["demos"]][:dialogs]]
    stubs = {f"{a}(" for a in domain["system_actions"]}
    calls = sorted({line.strip() for p in programs for line in p.splitlines()
                    if line.startswith("system.") and line.partition(".")[2].startswith(tuple(stubs))})
    for program in programs:
        lines = program.splitlines(keepends=True)
        for end, line in enumerate(lines):
            if line.startswith("system.") and end >= 2:
                yield "".join(lines[:end]), calls


def check_sgd_domain(engine: Engine, path: Path, dialogs: int, seen: Counter[str], prefixes: int | None = None
                     ) -> int:
    """Every rule set of the domain judged after each check of its first `dialogs` dialogs, or after a sample of
    `prefixes` of them (seeded by the domain's name, so a failure repeats); how many checks were compared."""
    domain = json.loads(path.read_text())
    checks = list(sgd_checks(domain, dialogs))
    if prefixes is not None and prefixes < len(checks):
        picked = sorted(random.Random(path.stem).sample(range(len(checks)), prefixes))
        checks = [checks[i] for i in picked]
    sets = sgd_rule_sets(engine, domain)
    for rules, decided_by in sets:
        for history, calls in checks:
            compare(engine, {"spec": domain["spec_program"], "preconditions": rules, "decided": decided_by,
                             "history": history, "calls": calls}, seen)
    return len(sets) * len(checks)
