"""The embedded guard answers as the service does: every set, history and call of the tool-call data, judged by
`Guard` (in this process, its state built message by message) and by `/check-actions` with the stored set on a
real stack (Redis, gateway, a worker with the real sandbox). Verdicts must be equal field for field: allowed,
the rules that refuse, the error texts of rules that raise, the `decided` labels and the rendered call; on the
fixtures, so must be where a history already broke a rule (`history_violation`).

The sets: the rules learned from the fixture's successful runs under each configuration of `precond eval tools`;
every condition the enumerator proposes for the fixture's actions with `options.now` (kept or not, stored with
`force`, 32 an action a set), which includes rules that raise (`KeyError`), reads of tables a call's rules fill
and comprehensions over the results; and the hand-written cancellation clause and collection conditions.
With the development data (`../shared/data/tau-airline`, or
PRECOND_DATA_DIR), also all 133 state-changing calls of its 120 runs under the rules learned from them, without
and with its labelled calls.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable, Collection, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import pytest

from precond.convert.openai import Converted
from precond.evaluation import tools, tools_labels
from precond.evaluation.settings import DataSettings
from precond.stack.local import Stack, make_stack, serving
from precond_client import Client, PreconditionSet
from precond_client.guard import Guard
from precond_client.schemas import InferOptions, InferRequest, InferResponse

TAU = Path(__file__).resolve().parents[1] / "fixtures" / "tau_airline"
READ = "reservation_id in self.results['get_reservation_details']"
RESERVATION = "self.results['get_reservation_details'][reservation_id]"
CLAUSE = {"AGENT.cancel_reservation": [READ, f"{READ} and ({RESERVATION}['cabin'] == 'business' or "
                                             f"{RESERVATION}['insurance'] == 'yes')",
                                       f"{RESERVATION}['created_at'] >= '2024-05-14T15:00:00'"],
          "AGENT.update_reservation_flights": [
              f"{READ} and {{(x['flight_number'], x['date']) for x in flights}} == "
              f"{{(x['flight_number'], x['date']) for x in {RESERVATION}['flights']}}",
              f"{READ} and all(x['date'] >= '2024-05-15' for x in {RESERVATION}['flights'])",
              f"all(x['origin'] >= '2024-05-15' for x in {RESERVATION}['flights'])",  # raises KeyError
              "len([x for x in flights if 'HAT0' in x['flight_number']]) <= 1"],
          "AGENT.send_certificate": ["user_id in self.results['get_user_details']",
                                     "self.results['get_user_details'][user_id]['membership'] != 'regular'"]}
MAX_CALLS = 64
INFERRING = 2
Messages = list[dict[str, Any]]
CallsAt = Callable[[Messages, int], list[dict[str, Any]]]


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[Stack]:
    """Bodies and sets the size of the airline's 53 successful runs."""
    stack = make_stack(tmp_path_factory.mktemp("guard-stack"), tiny_model_dir, PRECOND_JOB_TIMEOUT_S="600",
                       PRECOND_MAX_BODY_BYTES="16000000", PRECOND_MAX_SET_BYTES="16000000",
                       PRECOND_MAX_SET_BYTES_PER_TENANT="256000000", PRECOND_TENANT_RATE_PER_S="1000",
                       PRECOND_WORKER_CONCURRENCY=str(INFERRING), PRECOND_TENANT_MAX_RUNNING=str(INFERRING))
    with serving(stack, workers=1):
        yield stack


@pytest.fixture(scope="module")
def client(stack: Stack) -> Iterator[Client]:
    with Client(stack.base_url, timeout=600) as client:
        yield client


def trajectories(data: Path) -> list[Messages]:
    return [record["traj"] for record in json.loads((data / "trajectories.json").read_text())]


def learned_sets(client: Client, converted: Converted, more: Iterable[InferResponse] = ()) -> list[PreconditionSet]:
    """The rules `precond eval tools` learns under each of its configurations (and those of `more` inferences),
    with the inference's evidence, so that each set labels its rules (`decided`). A call's verdict depends only on
    its action's rules and labels, so the sets hold every distinct (rules, evidence) of each action once: set k has
    the k-th of each action."""
    inferences = infer_all(client, [tools.infer_request(converted, config) for config in tools.CONFIGS])
    variants: dict[str, list[tuple[list[str], dict[str, Any]]]] = {}
    for inferred in [*inferences, *more]:
        for action in sorted({*inferred.preconditions, *inferred.evidence, *(f"AGENT.{w}" for w in tools.WRITES)}):
            found = (inferred.preconditions.get(action, []),
                     {rule: e.model_dump() for rule, e in inferred.evidence.get(action, {}).items()})
            if found not in variants.setdefault(action, []):
                variants[action].append(found)
    bodies = [{"spec": converted.spec, "preconditions": {a: v[k][0] for a, v in variants.items() if k < len(v)},
               "evidence": {a: v[k][1] for a, v in variants.items() if k < len(v)}}
              for k in range(max(len(v) for v in variants.values()))]
    # a set without any rule is refused (it would allow everything); an action without rules is in the others
    return [client.create_set(body) for body in bodies if any(body["preconditions"].values())]


def every_condition(client: Client, converted: Converted) -> list[PreconditionSet]:
    """Every condition the enumerator proposes on the fixture (kept or dropped), 32 an action a set."""
    request = InferRequest(spec=converted.spec, demonstrations=[t.program for t in converted.trajectories],
                           options=InferOptions(generators=["enumerate"], candidates="all", tolerance=0,
                                                now=tools.NOW))
    candidates = client.infer_preconditions(request, timeout=600).candidates
    atoms = {action: list(dict.fromkeys(c.assertion for c in reports)) for action, reports in candidates.items()}
    assert sum(len(a) for a in atoms.values()) > 500, {a: len(r) for a, r in atoms.items()}
    chunks = [{a: rules[k: k + 32] for a, rules in atoms.items() if rules[k: k + 32]}
              for k in range(0, max(len(r) for r in atoms.values()), 32)]
    return [client.create_set({"spec": converted.spec, "preconditions": chunk, "force": True}) for chunk in chunks]


def compare_sets(client: Client, sets: list[PreconditionSet], runs: list[Messages],
                 calls_for: Callable[[PreconditionSet], CallsAt], history: bool = False
                 ) -> tuple[list[int], Counter[str]]:
    """`compare` on each set, `INFERRING` sets at a time (each set's calls and sessions are its own): how many
    calls each, and the kinds of verdict seen over all."""
    with ThreadPoolExecutor(INFERRING) as pool:
        done = list(pool.map(lambda stored: compare(client, stored, runs, calls_for(stored), history), sets))
    return [compared for compared, _ in done], sum((seen for _, seen in done), Counter())


def compare(client: Client, stored: PreconditionSet, runs: list[Messages], calls_at: CallsAt,
            history: bool = False) -> tuple[int, Counter[str]]:
    """Each run's calls judged after each of its histories, by the service and by one embedded session per run
    that took the run's messages one at a time; how many calls, and the kinds of verdict seen. `history`: also
    where the history already broke a rule (the session's, and `Guard.check_actions`' whole answer, against the
    service's `history_violation`)."""
    compared = 0
    seen: Counter[str] = Counter()
    guard = Guard.from_set(stored)
    for run in runs:
        session = guard.session()
        for index, message in enumerate(run):
            calls = calls_at(run, index)
            for first in range(0, len(calls), MAX_CALLS):
                batch = calls[first: first + MAX_CALLS]
                answer = client.check_with_set(stored.reference, run[:index], batch)
                service = answer.results
                if history:
                    assert session.history_violation == answer.history_violation, (stored.reference, index)
                    whole = guard.check_actions(run[:index], batch)
                    assert whole.model_dump(exclude={"judged_by"}) == answer.model_dump(exclude={"judged_by"}), (
                        stored.reference, index)
                    seen.update(["history broken"] if answer.history_violation else [])
                for call, expected in zip(batch, service, strict=True):
                    embedded = session.check(call["name"], call["arguments"])
                    assert embedded.model_dump() == expected.model_dump(), (stored.reference, index, call)
                    seen.update(_kinds(expected.model_dump()))
                    compared += 1
            session.add(message)
    return compared, seen


def _kinds(verdict: dict[str, Any]) -> list[str]:
    kinds = ["allowed"] if verdict["allowed"] else []
    return kinds + [kind for kind, field in (("refused", "violations"), ("raised", "error"), ("labelled", "decided"))
                    if verdict[field]]


def fixture_calls(runs: list[Messages], actions: set[str]) -> CallsAt:
    """At every assistant message that calls tools: every distinct call of every run whose action has rules."""
    distinct = {json.dumps(c["function"], sort_keys=True): {"name": c["function"]["name"],
                                                             "arguments": c["function"]["arguments"]}
                for run in runs for m in run for c in m.get("tool_calls") or []}
    calls = [c for c in distinct.values() if f"AGENT.{c['name']}" in actions]
    return lambda run, index: calls if run[index].get("tool_calls") else []


def test_the_embedded_guard_judges_the_fixtures_as_the_service_does(client: Client) -> None:
    converted = tools.load(TAU)
    runs = trajectories(TAU)
    hand = client.create_set({"spec": converted.spec, "preconditions": CLAUSE})
    sets = [hand, *learned_sets(client, converted), *every_condition(client, converted)]
    _, seen = compare_sets(client, sets, runs, lambda stored: fixture_calls(runs, set(stored.preconditions)),
                           history=True)
    assert min(seen[k] for k in ("allowed", "refused", "raised", "labelled", "history broken")) > 0, seen


def state_changing_calls(run: Messages, index: int, actions: Collection[str] = ()) -> list[dict[str, Any]]:
    """The calls of a state-changing tool that the message at `index` makes (of `actions` only, when given)."""
    return [{"name": c["function"]["name"], "arguments": c["function"]["arguments"]}
            for c in run[index].get("tool_calls") or [] if c["function"]["name"] in tools.WRITES
            and (not actions or f"AGENT.{c['function']['name']}" in actions)]


@pytest.mark.timeout(3600)
def test_all_state_changing_airline_calls_under_the_learned_rules(client: Client) -> None:
    data = DataSettings().root / "tau-airline"
    if not (data / "trajectories.json").exists():
        pytest.skip(f"the development data is not here ({data}; PRECOND_DATA_DIR): the fixture test covers five "
                    "of its runs")
    converted = tools.load(data)
    runs = trajectories(data)
    assert sum(len(state_changing_calls(run, i)) for run in runs for i in range(len(run))) == 133
    sets = learned_sets(client, converted, labelled_inferences(client, converted, data))
    compared, seen = compare_sets(
        client, sets, runs, lambda stored: partial(state_changing_calls, actions=frozenset(stored.preconditions)))
    assert compared[0] == 133 and seen["allowed"] and seen["refused"], (compared, seen)


def labelled_inferences(client: Client, converted: Converted, data: Path) -> list[InferResponse]:
    """The rules learned with each half of the tasks' labelled calls as counterexamples (`precond eval tools
    --labels`), with `options.now`: separating rules over dates and collections."""
    records = json.loads((data / "labels.json").read_text())
    return infer_all(client, [tools_labels.infer_request(converted, records, half, True, "labels.json")
                              for half in tools_labels.halves(converted)])


def infer_all(client: Client, requests: list[InferRequest]) -> list[InferResponse]:
    """The inferences in order, `INFERRING` at a time: they overlap on the worker's slots (what they infer does
    not depend on which runs beside which)."""
    with ThreadPoolExecutor(INFERRING) as pool:
        return list(pool.map(lambda request: client.infer_preconditions(request, timeout=600), requests))
