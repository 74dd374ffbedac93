"""Prior rules: rules learned for other services are candidates for a new one, judged on its own
demonstrations; they decide only what the demonstrations cannot."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from precond.engine.candidates.library import Library
from precond.engine.engine import Engine
from precond.engine.judging.report import UNSEEN_RULE
from precond.sandbox import Sandbox
from precond_client.schemas import (
    MAX_PRIOR_RULES,
    CheckRequest,
    InferOptions,
    InferRequest,
    InferResponse,
    PriorSource,
)
from precond_client.schemas.errors import InvalidInput, InvalidProgram

SPEC = """from collections import defaultdict
class USER:
  def __init__(self):
    self.no_more, self.selected = False, False
    self.intent, self.informed = defaultdict(lambda: False), defaultdict(lambda: False)
  def SELECT(self): self.selected = True
  def GOODBYE(self): self.no_more = True
  def INFORM(self, slot): self.informed[slot] = True
  def INFORM_INTENT(self, intent): self.intent[intent] = True

class SYSTEM:
  def __init__(self, user):
    self.user, self.query_success = user, None
  def search_result(self, ok): self.query_success = ok
  def SEARCH(self): pass
  def OFFER(self): pass
  def REQUEST(self, slot): pass
  def GOODBYE(self): pass
  def NOTIFY_FAILURE(self): pass
"""


def _dialog(first: str, second: str) -> str:
    return "\n".join([
        "user = USER()", "system = SYSTEM(user)", "user.INFORM_INTENT('find')",
        f"system.REQUEST({first!r})", f"user.INFORM({first!r})", f"system.REQUEST({second!r})",
        f"user.INFORM({second!r})", "system.SEARCH()", "system.search_result(True)", "system.OFFER()",
        "user.SELECT()", "user.GOODBYE()", "system.GOODBYE()",
    ]) + "\n"


DEMOS = [_dialog("city", "date"), _dialog("date", "city"), _dialog("city", "date"), _dialog("date", "city")]
RESTAURANTS = Path(__file__).resolve().parents[1] / "fixtures" / "data" / "sgd" / "Restaurants_1.json"
PINNED = Path(__file__).resolve().parent / "data" / "restaurants_enumerate_cautious.json"


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    """Without the shipped rule library: these tests pin what the demonstrations alone give (test_library.py
    tests the library)."""
    with Sandbox(workers=2) as sandbox:
        engine = Engine(sandbox, None)
        engine.library = Library()
        yield engine


def _infer(engine: Engine, **options: Any) -> InferResponse:
    return engine.infer(InferRequest(spec=SPEC, demonstrations=DEMOS,
                                     options=InferOptions(generators=["enumerate"], **options)))


def test_without_priors_the_default_answer_is_what_it_was(engine: Engine) -> None:
    """Pinned from the commit before priors existed (enumerate/cautious on the Restaurants fixture)."""
    data = json.loads(RESTAURANTS.read_text())
    demos = [d["program"] for d in data["demos"]]
    response = engine.infer(InferRequest(spec=data["spec_program"], demonstrations=demos,
                                         options=InferOptions(generators=["enumerate"])))
    pinned = json.loads(PINNED.read_text())
    assert response.preconditions == pinned["preconditions"]
    assert {a: {r: e.decided for r, e in ev.items()} for a, ev in response.evidence.items()} == pinned["decided"]
    assert response.warnings == pinned["warnings"]


def test_a_never_demonstrated_action_takes_the_prior_and_names_its_source(engine: Engine) -> None:
    alone = _infer(engine)
    assert alone.preconditions["SYSTEM.NOTIFY_FAILURE"] == [UNSEEN_RULE]
    response = _infer(engine, prior_rules={"SYSTEM.NOTIFY_FAILURE": ["not self.query_success"]})
    assert response.preconditions["SYSTEM.NOTIFY_FAILURE"] == ["not self.query_success"]
    evidence = response.evidence["SYSTEM.NOTIFY_FAILURE"]["not self.query_success"]
    assert (evidence.decided, evidence.source) == ("transferred", "options.prior_rules")
    assert "transferred" in response.warnings["SYSTEM.NOTIFY_FAILURE"]


def test_a_prior_the_demonstrations_contradict_is_refuted_with_its_evidence(engine: Engine) -> None:
    alone = _infer(engine)
    response = _infer(engine, prior_rules={"SYSTEM.OFFER": ["self.query_success is False"]}, candidates="all")
    assert response.preconditions["SYSTEM.OFFER"] == alone.preconditions["SYSTEM.OFFER"]
    report = next(c for c in response.candidates["SYSTEM.OFFER"] if c.assertion == "self.query_success is False")
    assert report.source == "prior" and not report.kept
    assert report.evidence is not None and report.evidence.holds == 0 and report.evidence.verdict == "refuted"


def test_a_disjunctive_prior_stays_a_disjunction(engine: Engine) -> None:
    """GOODBYE after "no more" *or* after a selection: the demonstrations only show both together."""
    prior = "self.user.no_more or self.user.selected"
    response = _infer(engine, prior_rules={"SYSTEM.GOODBYE": [prior]})
    assert response.preconditions["SYSTEM.GOODBYE"] == [prior]
    assert response.evidence["SYSTEM.GOODBYE"][prior].decided == "transferred"


def test_sources_vote_and_the_majority_reading_wins(engine: Engine) -> None:
    sources = [PriorSource(source="ps_a@1", rules={"SYSTEM.NOTIFY_FAILURE": ["not self.query_success"]}),
               PriorSource(source="ps_b@2", rules={"SYSTEM.NOTIFY_FAILURE": ["not self.query_success"]}),
               PriorSource(source="ps_c@1", rules={"SYSTEM.NOTIFY_FAILURE": ["self.query_success is None"]})]
    response = _infer(engine, prior_sources=sources)
    assert response.preconditions["SYSTEM.NOTIFY_FAILURE"] == ["not self.query_success"]
    assert response.evidence["SYSTEM.NOTIFY_FAILURE"]["not self.query_success"].source == "ps_a@1, ps_b@2"


def test_tied_priors_that_contradict_each_other_are_no_majority(engine: Engine) -> None:
    """One service guessed `is None`, another `is not None`: kept together they would refuse the notice
    everywhere. Neither is preferred; the reading they both allow stays."""
    sources = [PriorSource(source="ps_a@1", rules={"SYSTEM.NOTIFY_FAILURE": ["self.query_success is None"]}),
               PriorSource(source="ps_b@1", rules={"SYSTEM.NOTIFY_FAILURE": ["self.query_success is not None"]}),
               PriorSource(source="ps_c@1", rules={"SYSTEM.NOTIFY_FAILURE": ["not self.query_success"]})]
    response = _infer(engine, prior_sources=sources)
    assert response.preconditions["SYSTEM.NOTIFY_FAILURE"] == ["not self.query_success"]


def test_a_prior_naming_what_this_spec_does_not_define_is_dropped_with_a_reason(engine: Engine) -> None:
    alone = _infer(engine)
    response = _infer(engine, prior_rules={
        "SYSTEM.OFFER": ["self.user.informed['zip']", "self.user.verified", "slot == 'city'"],
        "SYSTEM.BOOK": ["self.user.selected"],  # another service's action: does not apply here
        "SYSTEM.NOTIFY_FAILURE": ["False"]})
    assert response.preconditions == alone.preconditions
    warning = response.warnings["SYSTEM.OFFER"]
    assert "'zip'" in warning and "'verified'" in warning and "'slot'" in warning
    assert "constant" in response.warnings["SYSTEM.NOTIFY_FAILURE"]


@pytest.mark.parametrize("rule", ["__import__('os').system('id')", "open('/etc/passwd')", "self.user.selected and",
                                  "(lambda: True)()"])
def test_a_prior_that_does_not_parse_or_calls_something_is_bad_input_naming_it(engine: Engine, rule: str) -> None:
    with pytest.raises(InvalidProgram) as caught:
        _infer(engine, prior_rules={"SYSTEM.OFFER": ["self.query_success", rule]})
    assert caught.value.field == "options.prior_rules[SYSTEM.OFFER][1]"


def test_prior_sets_must_be_resolved_by_the_service(engine: Engine) -> None:
    with pytest.raises(InvalidInput) as caught:
        _infer(engine, prior_sets=["ps_" + "0" * 24])
    assert caught.value.field == "options.prior_sets"


def test_the_number_of_prior_rules_is_bounded() -> None:
    rules = {f"SYSTEM.A{i}": ["self.query_success"] * 32 for i in range(MAX_PRIOR_RULES // 32)}
    InferOptions(prior_rules=rules)
    with pytest.raises(ValueError, match=f"at most {MAX_PRIOR_RULES}"):
        InferOptions(prior_rules=rules, prior_sources=[PriorSource(source="x", rules={"SYSTEM.B": ["True"]})])


def test_a_prior_trigger_joins_an_established_disjunction_as_one_more_alternative(engine: Engine) -> None:
    """"Anything else?" after a thanks or after a decline (a disjunction the demonstrations establish); two other
    services learned it after a selection. Conjoined, their rule would refuse the question after a thanks that
    followed no selection; it is one more thing that enables the question."""
    from tests.engine.test_cautious import SHOP_DEMOS_NO_FAILURE, SHOP_SPEC

    sources = [PriorSource(source=s, rules={"SYSTEM.REQ_MORE": ["self.user.selected"]}) for s in ("ps_a@1", "ps_b@1")]
    response = engine.infer(InferRequest(spec=SHOP_SPEC, demonstrations=SHOP_DEMOS_NO_FAILURE, options=InferOptions(
        generators=["enumerate"], prior_sources=sources)))
    (rule,) = response.preconditions["SYSTEM.REQ_MORE"]
    assert set(rule.split(" or ")) == {"self.user.thanked", "self.user.declined", "self.user.selected"}
    assert response.evidence["SYSTEM.REQ_MORE"][rule].decided == "established"
    report = next(c for c in response.candidates["SYSTEM.REQ_MORE"] if c.assertion == rule)
    assert report.reason and "joined by the prior rules' alternatives" in report.reason


def test_a_prior_common_at_this_services_calls_does_not_replace_what_they_established(engine: Engine) -> None:
    """The offer follows the search's success here (established). Another service's reading of that state
    also holds wherever the intent was stated, almost everywhere in these dialogs (not separated from chance at
    these calls): it is not this service's reading, and replacing the established rule with it would allow an
    offer before any search."""
    from tests.engine.test_cautious import SHOP_DEMOS, SHOP_SPEC

    prior = "self.success or self.user.intent['book']"
    sources = [PriorSource(source=s, rules={"SYSTEM.OFFER": [prior]}) for s in ("ps_a@1", "ps_b@1", "ps_c@1")]
    response = engine.infer(InferRequest(spec=SHOP_SPEC, demonstrations=SHOP_DEMOS, options=InferOptions(
        generators=["enumerate"], prior_sources=sources, candidates="all")))
    rules = response.preconditions["SYSTEM.OFFER"]
    assert "self.success" in rules
    assert response.evidence["SYSTEM.OFFER"]["self.success"].decided == "established"
    report = next(c for c in response.candidates["SYSTEM.OFFER"] if c.assertion == prior)
    assert report.evidence is not None and report.evidence.verdict == "chance"
    before_search = [{"actor": "user", "act": "INFORM_INTENT", "args": ["book"]},
                     {"actor": "user", "act": "INFORM", "args": ["city"]}]
    verdict = engine.check(CheckRequest(spec=SHOP_SPEC, preconditions=response.preconditions, history=before_search,
                                        calls=["system.OFFER()"])).results[0]
    assert verdict.error is None and not verdict.allowed
