"""The gateway's own judgement of a check (`interpreted`, the restricted interpreter) answers as the worker does
(`Engine.check` with the real sandbox): every verdict, violation, error text, `decided` label, `rule_status` and
`history_violation` equal, field for field, with only `judged_by` telling them apart.

The checks here: every SGD fixture domain under every condition the enumerator proposes for it (32 an action a
set, with hand-written rules that raise and read tables their own call fills) and under its learned rules, every
system call of its dialogs judged after every prefix (before a system call) of its first 4 dialogs, test dialogs
first; the tau-bench airline fixture under the learned rules and the hand-written clauses of the embedded guard's
differential test, each call judged after every prefix of its run. The development domains (every SGD one, the
tau-bench airline and retail runs) are judged alike in test_interpreted_differential_development.py.
A check the interpreter cannot take is answered `offload.Queued`: each comparison (precond/stack/differential.py)
fails on it, so a shape the recogniser stops accepting fails the test.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any

import pytest

from precond.convert.openai import convert
from precond.engine import checking as checking_module
from precond.engine.engine import Engine
from precond.engine.scope import scoped
from precond.evaluation import tools
from precond.sandbox import Sandbox
from precond.stack.differential import TAG, check_sgd_domain, compare, labels
from precond_client.schemas import CheckRequest
from tests.client.test_guard_differential import CLAUSE, MAX_CALLS, fixture_calls

pytestmark = pytest.mark.long  # collected first: pytest-xdist starts it first

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
SGD_FIXTURES = FIXTURES / "data" / "sgd"
@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def test_sgd_fixtures_are_judged_as_the_sandbox_judges_them(engine: Engine) -> None:
    seen: Counter[str] = Counter()
    for path in sorted(SGD_FIXTURES.glob("*.json")):
        check_sgd_domain(engine, path, 4, seen)
    assert min(seen[k] for k in ("allowed", "refused", "raised", "labelled", "history broken")) > 0, seen


# ---- tau-bench -------------------------------------------------------------------------------------------------
def writes_of(run: list[dict[str, Any]], index: int, writes: Collection[str], actions: Collection[str]
              ) -> list[dict[str, Any]]:
    """The calls of a state-changing tool with rules that the message at `index` makes."""
    return [{"name": c["function"]["name"], "arguments": c["function"]["arguments"]}
            for c in run[index].get("tool_calls") or []
            if c["function"]["name"] in writes and f"AGENT.{c['function']['name']}" in actions]


def tau_checks(runs: list[list[dict[str, Any]]], actions: Collection[str], writes: Collection[str] | None
               ) -> Iterator[tuple[list[dict[str, Any]], list[dict[str, Any]]]]:
    """(history, calls) at every message that calls a tool: its own state-changing calls (of `writes`), or (None)
    every distinct call of the runs whose action has rules."""
    every = fixture_calls(runs, set(actions))
    for run in runs:
        for index in range(len(run)):
            calls = every(run, index) if writes is None else writes_of(run, index, writes, actions)
            for first in range(0, len(calls), MAX_CALLS):
                yield run[:index], calls[first: first + MAX_CALLS]


def check_tau(engine: Engine, data: Path, hand: dict[str, list[str]], every_call: bool, seen: Counter[str],
              runs_at_most: int | None = None) -> None:
    """The learned rules (from the successful runs) and the hand-written ones, over the domain's state-changing
    tools (the airline's as `precond eval tools` names them, else the converter's by verb)."""
    records = json.loads((data / "trajectories.json").read_text())[:runs_at_most]
    airline = data.name.endswith("airline")
    converted = convert(records, json.loads((data / "tools.json").read_text()), "trajectories.json", "tools.json",
                        set(tools.WRITES) if airline else None)
    request = tools.infer_request(converted, tools.CONFIGS[0])
    if not airline:
        request = request.model_copy(update={"actions": [f"AGENT.{w}" for w in sorted(converted.writes)]})
    with scoped(TAG):
        learned = engine.infer(request)
    runs = [record["traj"] for record in records]
    for rules, decided in ((learned.preconditions, labels(learned)), (hand, {})):
        for history, calls in tau_checks(runs, list(rules), None if every_call else converted.writes):
            compare(engine, {"spec": converted.spec, "preconditions": rules, "decided": decided,
                             "history": history, "calls": calls}, seen)


def test_the_airline_fixture_is_judged_as_the_sandbox_judges_it(engine: Engine) -> None:
    seen: Counter[str] = Counter()
    check_tau(engine, FIXTURES / "tau_airline", CLAUSE, True, seen)
    assert min(seen[k] for k in ("allowed", "refused", "raised", "labelled", "history broken")) > 0, seen


def test_the_worker_does_not_screen_a_check_again(engine: Engine, monkeypatch: pytest.MonkeyPatch) -> None:
    """The gateway screened the job before it queued it (`offload.screened_check`): the worker's run skips it."""
    def screened_twice(*args: object) -> None:
        raise AssertionError("screened again")

    monkeypatch.setattr(checking_module, "check_calls", screened_twice)
    monkeypatch.setattr(checking_module, "check_preconditions", screened_twice)
    body = json.loads((FIXTURES.parent.parent / "examples" / "check-actions.json").read_text())
    with scoped(TAG):
        assert engine.check(CheckRequest.model_validate(body), screened=True).results
        with pytest.raises(AssertionError, match="screened again"):
            engine.check(CheckRequest.model_validate(body))
