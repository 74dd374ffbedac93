"""The engine against the real sandbox and real data (model-free paths, and Algorithm 1 with a scripted model)."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest

from precond.engine.candidates.library import Library
from precond.engine.engine import Engine
from precond.engine.scope import scoped
from precond.engine.spec import parse_spec, skip_statements
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferRequest, InferResponse, ModelInfo, NextActionRequest
from precond_client.schemas.errors import Cancelled, InvalidInput, InvalidProgram, UnknownAction
from tests.engine.conftest import SHARED
from tests.sandbox.warm_probe import COUNTING_SPEC

pytestmark = pytest.mark.long  # collected first: pytest-xdist starts it first


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    """Without the shipped rule library: these tests pin what the demonstrations alone give (test_library.py
    tests the library)."""
    with Sandbox(workers=2) as sandbox:
        engine = Engine(sandbox, None)
        engine.library = Library()
        yield engine


def _without_exceptions(demos: list[str], response: InferResponse) -> list[str]:
    steps: dict[int, set[int]] = {}
    for rules in response.evidence.values():
        for evidence in rules.values():
            for x in evidence.exceptions:
                steps.setdefault(x.demonstration, set()).add(x.position)
    return [skip_statements(d, steps.get(i, set())) for i, d in enumerate(demos)]


def _infer(data: dict[str, Any], **options: Any) -> InferRequest:
    return InferRequest(
        spec=data["spec_program"],
        demonstrations=[d["program"] for d in data["demos"]],
        options={"generators": ["enumerate"], **options},
    )


@pytest.mark.parametrize("ranking", ["subsumption", "recency", "marginal"])
def test_enumerate_infers_runnable_preconditions(engine: Engine, restaurants: dict[str, Any], ranking: str) -> None:
    response = engine.infer(_infer(restaurants, ranking=ranking))
    assert set(response.preconditions) == {f"SYSTEM.{a}" for a in restaurants["system_actions"]}
    assert "self.user.requested_slot[slot]" in response.preconditions["SYSTEM.INFORM"]
    assert response.preconditions["SYSTEM.GOODBYE"] == ["self.user.no_more"]
    # the program with the kept assertions runs every demonstration, but for the exceptions its rules tolerate
    # (the engine verified it; check it again)
    engine._sandbox.trace(response.program, _without_exceptions([d["program"] for d in restaurants["demos"]],
                                                                response))
    counts = response.stats.total
    assert counts.sampled >= counts.parsed >= counts.valid >= counts.clusters >= counts.kept > 0
    kept = [c for cands in response.candidates.values() for c in cands if c.kept]
    assert len(kept) == counts.kept and all(c.valid and c.cluster is not None for c in kept)
    assert {"trace", "enumerate", "validate", "rank"} <= set(response.stats.seconds)


def test_subsumption_is_at_least_as_tight_as_recall_aware_rankings(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    tight = engine.infer(_infer(restaurants, ranking="subsumption")).preconditions
    loose = engine.infer(_infer(restaurants, ranking="recency")).preconditions
    assert sum(map(len, tight.values())) >= sum(map(len, loose.values()))
    for action, kept in loose.items():
        assert set(kept) <= set(tight[action]), action


def test_a_demonstration_that_raises_names_its_index_and_line(engine: Engine, restaurants: dict[str, Any]) -> None:
    demos = [d["program"] for d in restaurants["demos"][:3]]
    demos[1] = demos[1] + "system.DANCE()\n"
    with pytest.raises(InvalidProgram) as err:
        engine.infer(InferRequest(spec=restaurants["spec_program"], demonstrations=demos,
                                  options={"generators": ["enumerate"]}))
    assert err.value.field == "demonstrations[1]"
    assert f"line {demos[1].count(chr(10))}" in err.value.message and "AttributeError" in err.value.message


def test_unknown_action_is_refused_before_any_work(engine: Engine, restaurants: dict[str, Any]) -> None:
    request = _infer(restaurants).model_copy(update={"actions": ["SYSTEM.DANCE"]})
    with pytest.raises(UnknownAction):
        engine.infer(request)


def _gt(data: dict[str, Any]) -> dict[str, list[str]]:
    return {f"SYSTEM.{a}": list(asserts) for a, asserts in data["gt_preconditions"].items()}


def test_check_reports_allowed_calls_and_violated_assertions(engine: Engine, restaurants: dict[str, Any]) -> None:
    history = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')\nuser.INFORM('city')\n"
    response = engine.check(CheckRequest(
        spec=restaurants["spec_program"], preconditions=_gt(restaurants), history=history,
        calls=["system.REQUEST('cuisine')", "system.REQUEST('city')", "system.FindRestaurants()"],
    ))
    verdicts = {r.call: r for r in response.results}
    assert verdicts["system.REQUEST('cuisine')"].allowed
    assert verdicts["system.REQUEST('city')"].violations == ["not self.user.informed_slot[slot]"]
    assert verdicts["system.FindRestaurants()"].violations == ["self.user.informed_slot['cuisine']"]


def test_checks_reuse_a_warm_child_of_their_tenant_only() -> None:
    """The worker runs each job in its tenant's scope; the check passes it to the sandbox, whose warm child of
    that tenant (and of no other) answers the tenant's next check. The spec counts in a shared module how
    often its process ran `mark`: 1 in a fresh child. A job whose result is shared between tenants runs with
    `warm=False`: a fresh child, even where its tenant has a warm one."""
    request = CheckRequest(spec=COUNTING_SPEC, preconditions={"Room.enter": ["self.marks == 1"]},
                           history="room = Room()\nroom.mark()\n", calls=["room.enter()"])
    with Sandbox(workers=1) as sandbox:
        engine = Engine(sandbox, None)

        def allowed(tenant: str, warm: bool = True) -> bool:
            with scoped(tenant, warm):
                return engine.check(request).results[0].allowed

        assert [allowed("tenant-a"), allowed("tenant-a"), allowed("tenant-b"), allowed(""),
                allowed("tenant-a", warm=False), allowed("tenant-a")] == [True, False, True, True, True, False]


class ScriptedModel:
    """A stand-in for the code model that answers from a script; the sandbox and Algorithm 1 are real."""

    info = ModelInfo(name="scripted", device="cpu", dtype="none")
    known_calls: tuple[str, ...] = ()

    def __init__(self, greedy: str, samples: Sequence[str]) -> None:
        self.greedy, self.samples = greedy, list(samples)
        self.calls: list[tuple[int, float]] = []

    def complete(self, prefix: str, suffixes: Sequence[str], n: int, sampling: Any, stop: str,
                 should_stop: Callable[[], bool] | None = None) -> list[list[str]]:
        self.calls.append((n, sampling.temperature))
        if sampling.temperature == 0:
            return [[self.greedy]]
        return [self.samples[:n]]


def _next(data: dict[str, Any], model: ScriptedModel, **options: Any) -> list[Any]:
    history = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')\nuser.INFORM('city')\n"
    with Sandbox(workers=1) as sandbox:
        engine = Engine(sandbox, lambda: model)  # type: ignore[arg-type,return-value]
        response = engine.next_action(NextActionRequest(
            spec=data["spec_program"], preconditions=_gt(data), demonstrations=[data["demos"][0]["program"]],
            history=history, options={"mode": "sample", **options},
        ))
    return response.actions


class ThinkingModel(ScriptedModel):
    """Writes `thought` where it is asked to continue a `# think:` line and, asked for its next line, the lines of
    `next_lines` in turn (then the greedy call); records every text it continues."""

    def __init__(self, thought: str, greedy: str, next_lines: Sequence[str] = ()) -> None:
        super().__init__(greedy, [])
        self.thought, self.next_lines, self.asked = thought, list(next_lines), []

    def complete(self, prefix: str, suffixes: Sequence[str], n: int, sampling: Any, stop: str,
                 should_stop: Callable[[], bool] | None = None) -> list[list[str]]:
        self.asked.append(prefix + suffixes[0])
        if suffixes[0].strip() == "# think:":
            return [[self.thought]]
        if self.next_lines:
            return [[self.next_lines.pop(0)]]
        return super().complete(prefix, suffixes, n, sampling, stop, should_stop)


def test_react_thinks_before_the_action_and_the_thought_cannot_leave_its_comment(restaurants: dict[str, Any]) -> None:
    """The thought is the model's text: a line break in it would end the comment and make the rest of it a
    statement of the history the sandbox runs. It is kept to printable characters, one line."""
    model = ThinkingModel(" The user gave a city.\r\nimport os\x00\u2028os.system('x')", "system.REQUEST('cuisine')")
    [action] = _next(restaurants, model, think=True)
    assert action.thoughts == ["The user gave a city.import osos.system('x')"]
    assert (action.call, action.verified) == ("system.REQUEST('cuisine')", True)
    assert model.asked[0].endswith("user.INFORM('city')\n# think:")  # asked to think right after the history
    assert model.asked[-1].endswith(f"# think: {action.thoughts[0]}\n")  # then to act after its thought


def test_react_keeps_the_thoughts_the_model_writes_in_a_row_up_to_three(restaurants: dict[str, Any]) -> None:
    model = ThinkingModel("The plan.", "system.REQUEST('cuisine')", ["# think: Where to look.", "#think:\rMore."])
    [action] = _next(restaurants, model, think=True)
    assert action.thoughts == ["The plan.", "Where to look.", "More."]
    assert action.call == "system.REQUEST('cuisine')"
    assert len(model.asked) == 4  # the first thought, two more read as its next lines, no fourth: then the action
    assert model.asked[-1].endswith("# think: The plan.\n# think: Where to look.\n# think: More.\n")


def test_greedy_prediction_that_holds_is_verified_at_once(restaurants: dict[str, Any]) -> None:
    model = ScriptedModel("system.REQUEST('cuisine')", [])
    [action] = _next(restaurants, model)
    assert (action.call, action.verified, action.attempts, action.rejected) == (
        "system.REQUEST('cuisine')", True, 1, [])
    assert model.calls == [(1, 0.0)]


def test_random_samples_replace_a_greedy_action_that_violates(restaurants: dict[str, Any]) -> None:
    model = ScriptedModel("system.REQUEST('city')", ["user.INFORM('x')", "system.FindRestaurants()",
                                                     "system.REQUEST('cuisine')", "system.GOODBYE()"])
    [action] = _next(restaurants, model, max_attempts=5)
    assert (action.call, action.verified, action.attempts) == ("system.REQUEST('cuisine')", True, 4)
    assert [r.call for r in action.rejected] == ["system.REQUEST('city')", "user.INFORM('x')",
                                                 "system.FindRestaurants()"]
    assert action.rejected[0].violations == ["not self.user.informed_slot[slot]"]
    assert action.rejected[1].reason == "USER.INFORM is not an action function"


def test_nothing_verified_is_said_explicitly_not_answered_with_greedy(restaurants: dict[str, Any]) -> None:
    model = ScriptedModel("system.REQUEST('city')", ["system.GOODBYE()"] * 10)
    [action] = _next(restaurants, model, max_attempts=3)
    assert (action.call, action.verified, action.attempts, len(action.rejected)) == (None, False, 3, 3)
    assert action.reason and action.reason.startswith("no verified action")
    assert [r.call for r in action.rejected] == ["system.REQUEST('city')", "system.GOODBYE()", "system.GOODBYE()"]


def test_greedy_fallback_only_when_asked_and_only_for_an_action(restaurants: dict[str, Any]) -> None:
    model = ScriptedModel("system.REQUEST('city')", ["system.GOODBYE()"] * 10)
    [action] = _next(restaurants, model, max_attempts=3, fallback="greedy")
    assert (action.call, action.verified, action.attempts) == ("system.REQUEST('city')", False, 3)
    # a user act (or any line that is no call of an action) is never returned as the action
    model = ScriptedModel("user.INFORM('city')", ["system.GOODBYE()"] * 10)
    [action] = _next(restaurants, model, max_attempts=3, fallback="greedy")
    assert action.call is None and action.rejected[0].reason == "USER.INFORM is not an action function"
    [action] = _next(restaurants, model, verify=False)
    assert (action.call, action.verified) == (None, False)
    assert action.rejected[0].call == "user.INFORM('city')"


def test_a_turn_continues_until_the_model_hands_it_back(restaurants: dict[str, Any]) -> None:
    model = ScriptedModel("system.REQUEST('cuisine')", [])
    actions = _next(restaurants, model, max_actions=3)
    # the scripted greedy repeats the same call; REQUEST('cuisine') stays allowed (cuisine not informed)
    assert [a.call for a in actions] == ["system.REQUEST('cuisine')"] * 3
    model = ScriptedModel("user.INFORM('cuisine')", ["system.REQUEST('cuisine')"])
    actions = _next(restaurants, model, max_actions=3)
    assert [(a.call, a.verified, a.attempts) for a in actions] == [("system.REQUEST('cuisine')", True, 2)]


def test_a_history_that_broke_the_preconditions_is_still_a_valid_history(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    # what already happened is fact: REQUEST('city') after the user gave the city violates the GT rule,
    # yet the next calls are judged on the state it left
    history = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM('city')\nsystem.REQUEST('city')\n"
    response = engine.check(CheckRequest(
        spec=restaurants["spec_program"], preconditions=_gt(restaurants), history=history,
        calls=["system.REQUEST('city')", "system.REQUEST('cuisine')"],
    ))
    assert [(r.allowed, r.violations) for r in response.results] == [
        (False, ["not self.user.informed_slot[slot]"]), (True, [])]


def test_assertions_that_fail_together_are_dropped_until_the_program_runs(engine: Engine) -> None:
    # found with the model on Events_1: OFFER's assertion subscripts a defaultdict, inserting a key, so the
    # INFORM_COUNT assertion `len(...) == 1`, valid on its own, fails in the combined program
    events = json.loads((SHARED / "sgd" / "Events_1.json").read_text())
    demos = [d["program"] for d in events["demos"]]
    spec = parse_spec(events["spec_program"])
    preconditions = {
        "SYSTEM.OFFER": ["not self.user.informed_intent['BuyEventTickets']"],
        "SYSTEM.INFORM_COUNT": ["len(self.user.informed_intent) == 1", "self.query_success"],
    }
    program, kept, dropped = engine._verified_program(spec, preconditions, demos)
    assert kept["SYSTEM.INFORM_COUNT"] == ["self.query_success"]
    assert kept["SYSTEM.OFFER"] == ["not self.user.informed_intent['BuyEventTickets']"]
    assert list(dropped) == ["SYSTEM.INFORM_COUNT"]
    reason = dropped["SYSTEM.INFORM_COUNT"]["len(self.user.informed_intent) == 1"]
    assert reason.startswith("dropped: fails with the other")
    engine._sandbox.trace(program, demos)


def test_no_demonstration_calling_an_action_is_refused(engine: Engine, restaurants: dict[str, Any]) -> None:
    setup = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM('city')\n"
    request = InferRequest(spec=restaurants["spec_program"], demonstrations=[setup, setup],
                           options={"generators": ["enumerate"]})
    with pytest.raises(InvalidInput) as err:
        engine.infer(request)
    assert err.value.field == "demonstrations" and "none of the 2 demonstrations calls" in err.value.message


def test_an_action_without_occurrence_is_reported_not_silently_empty(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    demo = "user = USER()\nsystem = SYSTEM(user)\nsystem.REQUEST('city')\nuser.INFORM('city')\n"
    actions = ["SYSTEM.REQUEST", "SYSTEM.GOODBYE"]
    response = engine.infer(InferRequest(spec=restaurants["spec_program"], demonstrations=[demo], actions=actions,
                                         options={"generators": ["enumerate"], "guarded": actions}))
    assert set(response.warnings) == {"SYSTEM.GOODBYE", "SYSTEM.REQUEST"}  # REQUEST: called once
    assert response.warnings["SYSTEM.GOODBYE"].startswith("no occurrence: no demonstration calls SYSTEM.GOODBYE")
    assert response.preconditions["SYSTEM.GOODBYE"] == ["False"]  # options.unseen: "refuse" (the default)
    assert "refused" in response.warnings["SYSTEM.GOODBYE"]
    conversational = engine.infer(InferRequest(spec=restaurants["spec_program"], demonstrations=[demo],
                                               actions=actions, options={"generators": ["enumerate"]}))
    assert conversational.preconditions["SYSTEM.GOODBYE"] == []  # by default a goodbye is not guarded
    assert "never refused for want of a rule" in conversational.warnings["SYSTEM.GOODBYE"]


def _programs(data: dict[str, Any], n: int) -> list[str]:
    return [demo["program"] for demo in data["demos"][:n]]


def test_an_action_seen_too_rarely_or_left_without_a_rule_is_warned_of(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    """NOTIFY_FAILURE (called twice) and REQ_MORE (4 calls, no rule kept) get `[]` under the paper's ranking:
    each says why, at the top."""
    response = engine.infer(InferRequest(spec=restaurants["spec_program"], demonstrations=_programs(restaurants, 8),
                                         options={"generators": ["enumerate"], "ranking": "recency"}))
    assert response.preconditions["SYSTEM.NOTIFY_FAILURE"] == [] and response.preconditions["SYSTEM.REQ_MORE"] == []
    thin = response.warnings["SYSTEM.NOTIFY_FAILURE"]
    assert thin.startswith("thin evidence: SYSTEM.NOTIFY_FAILURE is called 2 time(s) in 2 demonstration(s)")
    assert thin.endswith("its rule is empty: every call of it is allowed")
    assert response.warnings["SYSTEM.REQ_MORE"].startswith("empty rule: no candidate condition for SYSTEM.REQ_MORE")
    assert all(a in response.warnings for a, rules in response.preconditions.items() if not rules)
    assert "SYSTEM.INFORM" not in response.warnings  # demonstrated often, with rules: nothing to say


def test_a_rule_resting_on_few_calls_is_warned_of_under_strict_validation(
    engine: Engine, restaurants: dict[str, Any]
) -> None:
    response = engine.infer(InferRequest(spec=restaurants["spec_program"], demonstrations=_programs(restaurants, 2),
                                         options={"generators": ["enumerate"], "tolerance": 0, "ranking": "recency",
                                                  "unseen": "allow"}))
    resting = [a for a, rules in response.preconditions.items() if rules and a in response.warnings]
    assert resting, response.warnings
    assert all("cannot tell a requirement from a coincidence" in response.warnings[a] for a in resting)


@pytest.mark.parametrize(("call", "words"), [
    ("user.AFFIRM()", "USER.AFFIRM is not one of the agent's actions"),
    ("system.REQUESTT('city')", "unknown action 'SYSTEM.REQUESTT' in calls[1] (did you mean 'SYSTEM.REQUEST'?)"),
])
def test_a_call_of_something_not_an_action_is_refused_never_approved(
    engine: Engine, restaurants: dict[str, Any], call: str, words: str
) -> None:
    request = CheckRequest(spec=restaurants["spec_program"], preconditions={}, calls=["system.GOODBYE()", call],
                           history="user = USER()\nsystem = SYSTEM(user)\n")
    with pytest.raises(UnknownAction) as err:
        engine.check(request)
    assert err.value.field == "calls[1]" and words in err.value.message


def test_check_names_the_line_and_rule_a_history_already_broke(engine: Engine, restaurants: dict[str, Any]) -> None:
    """The history is what happened (the calls are still judged after it), but a history that broke a rule says
    where and which: looked up before it was verified, the call that followed is not silently fine."""
    rules = {"SYSTEM.OFFER": ["self.query_success", "slot != ''"], "SYSTEM.GOODBYE": ["self.user.no_more"]}
    broken = ("user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')\n"
              "system.OFFER('restaurant_name')\nsystem.GOODBYE()\n")
    request = CheckRequest(spec=restaurants["spec_program"], preconditions=rules, history=broken,
                           calls=["system.REQUEST('city')"])
    answer = engine.check(request)
    assert answer.results[0].allowed
    assert answer.history_violation == ("history, line 4: system.OFFER('restaurant_name'): SYSTEM.OFFER's rule "
                                        "`self.query_success` did not hold")
    fine = request.model_copy(update={"history": "user = USER()\nsystem = SYSTEM(user)\nuser.GOODBYE()\n"
                                                 "system.GOODBYE()\n"})
    assert engine.check(fine).history_violation is None


def test_rule_errors_name_the_rule_and_give_a_hint(engine: Engine, restaurants: dict[str, Any]) -> None:
    history = "user = USER()\nsystem = SYSTEM(user)\n"

    def check(preconditions: dict[str, list[str]]) -> InvalidInput:
        with pytest.raises(InvalidInput) as err:
            engine.check(CheckRequest(spec=restaurants["spec_program"], preconditions=preconditions,
                                      history=history, calls=["system.GOODBYE()"]))
        return err.value

    wrong = check({"SYSTEM.GOODBYE": ["self.user.no_more", "assert self.user.no_more"]})
    assert wrong.field == "preconditions.SYSTEM.GOODBYE[1]"
    assert "write the expression without `assert`" in wrong.message
    unknown = check({"SYSTEM.GODBYE": ["self.user.no_more"]})
    assert isinstance(unknown, UnknownAction) and unknown.field == "preconditions.SYSTEM.GODBYE"
    assert "did you mean 'SYSTEM.GOODBYE'?" in unknown.message


@pytest.mark.parametrize("ranking", ["recency", "subsumption"])
def test_every_candidate_says_why_it_was_kept_or_dropped(
    engine: Engine, restaurants: dict[str, Any], ranking: str
) -> None:
    response = engine.infer(_infer(restaurants, ranking=ranking, tolerance=0, candidates="all"))
    reports = [c for cands in response.candidates.values() for c in cands]
    assert reports and all(c.reason for c in reports), [c.assertion for c in reports if not c.reason]
    kept = [c for c in reports if c.kept]
    assert kept and all(c.reason.startswith("kept") for c in kept if c.reason)
    reasons = [c.reason or "" for c in reports if not c.kept]
    assert any(r.startswith("violated at demonstrations[") and ", line " in r for r in reasons)
    assert any(r.startswith("subsumed by ") for r in reasons)
    assert any(r.startswith("equivalent to ") for r in reasons)
    if ranking == "recency":
        assert any("looks like a phase, not a requirement" in r for r in reasons)


def _slipped(data: dict[str, Any]) -> tuple[list[str], int, int]:
    """The demonstrations with one human slip: demonstration 2 re-asks the city the user already gave."""
    demos = [d["program"] for d in data["demos"]]
    lines = demos[2].splitlines()
    at = lines.index("user.INFORM('city')") + 1
    lines.insert(at, "system.REQUEST('city')")
    demos[2] = "\n".join(lines) + "\n"
    return demos, 2, at + 1


def test_a_single_slip_does_not_kill_a_true_rule(engine: Engine, restaurants: dict[str, Any]) -> None:
    demos, demo, line = _slipped(restaurants)
    rule = "not self.user.informed_slot[slot]"

    def infer(tolerance: float) -> Any:
        return engine.infer(InferRequest(spec=restaurants["spec_program"], demonstrations=demos,
                                         options={"generators": ["enumerate"], "tolerance": tolerance}))

    assert rule not in infer(0).preconditions["SYSTEM.REQUEST"]  # strict: the slip refutes it
    response = infer(0.05)
    assert rule in response.preconditions["SYSTEM.REQUEST"]  # kept, and not dropped by verification
    evidence = response.evidence["SYSTEM.REQUEST"][rule]
    assert evidence.verdict == "tolerated" and evidence.holds == evidence.occurrences - 1
    (exception,) = evidence.exceptions
    assert (exception.demonstration, exception.line, exception.call) == (demo, line, "system.REQUEST('city')")
    report = next(c for c in response.candidates["SYSTEM.REQUEST"] if c.assertion == rule)
    assert report.kept and report.valid and f"demonstrations[{demo}], line {line}" in (report.reason or "")
    # the returned program runs the demonstrations except at the recorded exception
    engine._sandbox.trace(response.program, _without_exceptions(demos, response))


def test_thin_evidence_keeps_no_coincidence_with_the_papers_criteria(engine: Engine,
                                                                     restaurants: dict[str, Any]) -> None:
    demos = [d["program"] for d in restaurants["demos"][:3]]
    response = engine.infer(InferRequest(spec=restaurants["spec_program"], demonstrations=demos,
                                         options={"generators": ["enumerate"], "ranking": "recency",
                                                  "unseen": "allow", "candidates": "all"}))
    thin = [a for a, reports in response.candidates.items()
            if any(c.evidence and 0 < c.evidence.occurrences < 3 for c in reports)]
    assert thin
    for action in thin:
        assert response.preconditions[action] == [], action
        assert all("too few to tell a rule from a coincidence" in (c.reason or "")
                   for c in response.candidates[action] if c.evidence and c.evidence.verdict == "thin")
    kept = [e for rules in response.evidence.values() for e in rules.values()]
    assert kept and all(e.occurrences >= 3 and 0 < e.confidence < 1 for e in kept)


def test_thin_evidence_gives_assumed_rules_with_the_cautious_criterion(engine: Engine,
                                                                       restaurants: dict[str, Any]) -> None:
    """One or two calls cannot establish a rule; the cautious default keeps what enabled them, as assumed, and
    says so in the warnings instead of leaving the action open."""
    demos = [d["program"] for d in restaurants["demos"][:3]]
    response = engine.infer(InferRequest(spec=restaurants["spec_program"], demonstrations=demos,
                                         options={"generators": ["enumerate"]}))
    thin = [a for a, reports in response.candidates.items()
            if any(c.evidence and 0 < c.evidence.occurrences < 3 for c in reports)]
    assumed = [a for a in thin if response.preconditions[a]]
    assert assumed
    for action in assumed:
        assert {e.decided for e in response.evidence[action].values()} == {"assumed"}, action
        assert "its rules are assumed" in response.warnings[action], response.warnings[action]


def test_demonstrations_that_refute_every_candidate_give_an_empty_rule_with_reasons(engine: Engine) -> None:
    spec = ("class A:\n  def __init__(self):\n    self.x = 0\n    self.on = False\n"
            "  def inc(self):\n    self.x += 1\n    self.on = not self.on\n  def act(self):\n    pass\n")
    demo = "a = A()\n" + "a.act()\na.inc()\n" * 4
    response = engine.infer(InferRequest(spec=spec, demonstrations=[demo], actions=["A.act"],
                                         options={"generators": ["enumerate"], "candidates": "all"}))
    assert response.preconditions["A.act"] == []
    reports = response.candidates["A.act"]
    assert reports and all(c.reason and not c.kept for c in reports)


class RecordingModel:
    """Answers every inference prompt with a plain `assert True` and records which actions were asked about."""

    info = ModelInfo(name="recording", device="cpu", dtype="none")
    known_calls: tuple[str, ...] = ()

    def __init__(self) -> None:
        self.asked: list[str] = []

    def complete(self, prefix: str, suffixes: Sequence[str], n: int, sampling: Any, stop: str,
                 should_stop: Callable[[], bool] | None = None) -> list[list[str]]:
        self.asked += suffixes
        return [[" True"] * n for _ in suffixes]


@pytest.mark.parametrize("model_for", ["thin", "all"])
def test_the_model_is_asked_only_about_thinly_demonstrated_actions_when_told(
    restaurants: dict[str, Any], model_for: str
) -> None:
    """Restaurants' first three demonstrations show INFORM twice and REQUEST eight times in all three: with
    `model_for: thin` only the thin one gets a prompt; with `all` (the paper) both do."""
    model = RecordingModel()
    demos = [d["program"] for d in restaurants["demos"][:3]]
    with Sandbox(workers=1) as sandbox:
        engine = Engine(sandbox, lambda: model)  # type: ignore[arg-type,return-value]
        trace = sandbox.trace(restaurants["spec_program"], demos)
        response = engine.infer(InferRequest(
            spec=restaurants["spec_program"], demonstrations=demos, actions=["SYSTEM.INFORM", "SYSTEM.REQUEST"],
            options={"model_for": model_for, "prompts_per_action": 1},
        ))
    counts = {a: len(trace.actions[a].occurrences) for a in ("SYSTEM.INFORM", "SYSTEM.REQUEST")}
    assert counts["SYSTEM.INFORM"] < 3 <= counts["SYSTEM.REQUEST"], counts
    asked = {a for a in counts
             if any(s.endswith(f"def {a.split('.')[1]}(self, slot):\n    assert") for s in model.asked)}
    assert asked == ({"SYSTEM.INFORM"} if model_for == "thin" else set(counts))
    assert response.preconditions["SYSTEM.REQUEST"]  # the enumerator still learns the well-evidenced rule
    # asked about the thin action only, the model reads the rule the evidence established for the other first
    # (with `all` there is none yet: the paper's prompt)
    shown = "  def REQUEST(self, slot):\n    assert not self.user.informed_slot[slot]\n  def INFORM(self, slot):"
    assert any(shown in s for s in model.asked) == (model_for == "thin")


def test_without_the_enumerator_the_model_is_asked_about_every_action(restaurants: dict[str, Any]) -> None:
    """`model_for: thin` narrows the model to what the enumerator cannot settle; with the model alone there is
    nobody else to propose, so it is asked about every action."""
    model = RecordingModel()
    demos = [d["program"] for d in restaurants["demos"][:3]]
    with Sandbox(workers=1) as sandbox:
        Engine(sandbox, lambda: model).infer(InferRequest(  # type: ignore[arg-type,return-value]
            spec=restaurants["spec_program"], demonstrations=demos, actions=["SYSTEM.INFORM", "SYSTEM.REQUEST"],
            options={"generators": ["model"], "model_for": "thin", "prompts_per_action": 1},
        ))
    assert any("def REQUEST(" in s for s in model.asked) and any("def INFORM(" in s for s in model.asked)


def test_a_job_waiting_for_the_models_load_stops_waiting_when_cancelled() -> None:
    """A worker takes a job while its model still loads (seconds for the embedded one): the job's cancellation
    takes effect within a poll of its wait, not when the load ends."""
    loading, release = threading.Event(), threading.Event()

    def slow_load() -> Any:
        loading.set()
        release.wait(30)
        return object()

    engine = Engine(None, slow_load)  # type: ignore[arg-type]  # no sandbox needed to wait for a model
    loader = threading.Thread(target=engine.model)
    loader.start()
    try:
        assert loading.wait(10)
        with pytest.raises(Cancelled):
            engine.model(cancelled=lambda: True)
        assert loader.is_alive() and not release.is_set()  # the load still goes on: the wait did not outlast it
    finally:
        release.set()
        loader.join()
