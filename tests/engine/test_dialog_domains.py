"""Three dialog services written from scratch (tests/fixtures/dialog_domains): each domain's rules are inferred
from its demonstrations with the shipped rule library, and every situation's verdict, written down before any
inference, is checked: a yes that answered no confirmation, a yes after the back-end said no, failure and success
notices without a result of their sign."""

from __future__ import annotations

import ast
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from precond.convert.sgd import Service, spec_program
from precond.engine.engine import Engine
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferOptions, InferRequest

DOMAINS = Path(__file__).parents[1] / "fixtures" / "dialog_domains"
NAMES = ("pharmacy", "shop", "clinic")


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def _domain(name: str) -> dict[str, Any]:
    domain: dict[str, Any] = json.loads((DOMAINS / f"{name}.json").read_text(encoding="utf-8"))
    return domain


def _event(statement: str) -> dict[str, Any]:
    """`user.INFORM('date')` as a structured history event."""
    call = ast.parse(statement, mode="eval").body
    assert isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute) and isinstance(call.func.value, ast.Name)
    return {"actor": call.func.value.id, "act": call.func.attr, "args": [ast.literal_eval(a) for a in call.args]}


def _verdicts(engine: Engine, name: str) -> list[tuple[str, bool, bool]]:
    """(why, written verdict, the inferred rules' verdict) of each situation."""
    domain = _domain(name)
    spec = spec_program(Service(domain["service"], domain["intents"], domain["slots"]))
    inferred = engine.infer(InferRequest(spec=spec, demonstrations=domain["demonstrations"],
                                         options=InferOptions(generators=["enumerate"])))
    out = []
    for situation in domain["situations"]:
        verdict = engine.check(CheckRequest(spec=spec, preconditions=inferred.preconditions,
                                            history=[_event(s) for s in situation["history"]],
                                            calls=[situation["call"]])).results[0]
        assert verdict.error is None, verdict.error
        out.append((f"{situation['call']}: {situation['why']}", situation["allowed"], verdict.allowed))
    return out


DISAGREE = {("pharmacy", 2): "a failure notice before anything was asked: the development domains' ground truths "
                             "allow it (`not self.query_success`), and the signed notice follows them"}
"""Written verdicts the learner does not meet, and why: each must keep failing (strict), so a fix is noticed."""


@pytest.fixture(scope="module")
def verdicts(engine: Engine) -> dict[str, list[tuple[str, bool, bool]]]:
    return {name: _verdicts(engine, name) for name in NAMES}


@pytest.mark.parametrize(("name", "k"), [
    pytest.param(name, k, marks=[pytest.mark.xfail(strict=True, reason=DISAGREE[(name, k)])]
                 if (name, k) in DISAGREE else []) for name in NAMES for k in range(5)])
def test_every_written_verdict_holds(verdicts: dict[str, list[tuple[str, bool, bool]]], name: str, k: int) -> None:
    why, written, inferred = verdicts[name][k]
    assert written == inferred, why
