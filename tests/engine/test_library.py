"""The rule library shipped with the service: rules learned on other domains are priors for a spec that shares
their vocabulary, marked as transferred with the domain they come from; the tenant's own priors come first."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from precond.engine.candidates.library import SIGNED, Library, LibrarySource, from_json, shipped, to_json
from precond.engine.engine import Engine
from precond.engine.judging.report import UNSEEN_RULE
from precond.sandbox import Sandbox
from precond_client.schemas import InferOptions, InferRequest, InferResponse

SPEC = """from collections import defaultdict
class USER:
  def __init__(self):
    self.no_more, self.selected = False, False
    self.informed = defaultdict(lambda: False)
  def SELECT(self): self.selected = True
  def GOODBYE(self): self.no_more = True
  def INFORM(self, slot): self.informed[slot] = True

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
        "user = USER()", "system = SYSTEM(user)",
        f"system.REQUEST({first!r})", f"user.INFORM({first!r})", f"system.REQUEST({second!r})",
        f"user.INFORM({second!r})", "system.SEARCH()", "system.search_result(True)", "system.OFFER()",
        "user.SELECT()", "user.GOODBYE()", "system.GOODBYE()",
    ]) + "\n"


DEMOS = [_dialog("city", "date"), _dialog("date", "city"), _dialog("city", "date"), _dialog("date", "city")]
FAILURE = "not self.query_success"
LIBRARY = Library((
    LibrarySource("Buses_9", {"NOTIFY_FAILURE": [FAILURE], "GOODBYE": ["self.user.no_more"], "OFFER": ["x"],
                              "REQUEST": ["not self.user.informed[slot]"]}),
    LibrarySource("Trains_9", {"NOTIFY_FAILURE": [FAILURE], "GOODBYE": ["self.user.no_more"],
                               "REQUEST": ["not self.user.informed[slot]"], "BOOK": ["self.user.affirmed"]}),
    LibrarySource("alfworld", {"goto": ["True"], "take": ["self.at(r)"], "put": ["self.holding(o)"]}),
))


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        engine = Engine(sandbox, None)
        engine.library = LIBRARY
        yield engine


def _infer(engine: Engine, **options: Any) -> InferResponse:
    return engine.infer(InferRequest(spec=SPEC, demonstrations=DEMOS,
                                     options=InferOptions(generators=["enumerate"], **options)))


def test_a_never_demonstrated_failure_notice_takes_the_library_rule_marked_transferred(engine: Engine) -> None:
    response = _infer(engine)
    assert response.preconditions["SYSTEM.NOTIFY_FAILURE"] == [FAILURE]
    evidence = response.evidence["SYSTEM.NOTIFY_FAILURE"][FAILURE]
    assert (evidence.decided, evidence.source) == ("transferred", "library:Buses_9, library:Trains_9")
    assert "transferred" in response.warnings["SYSTEM.NOTIFY_FAILURE"]


def test_without_the_library_the_action_has_no_rule_and_says_so(engine: Engine) -> None:
    response = _infer(engine, library=False)
    assert response.preconditions["SYSTEM.NOTIFY_FAILURE"] == [UNSEEN_RULE]
    assert all(e.source is None or not e.source.startswith("library:")
               for rules in response.evidence.values() for e in rules.values())


def test_the_tenants_own_priors_come_on_top(engine: Engine) -> None:
    own = "self.query_success is False"
    response = _infer(engine, prior_rules={"SYSTEM.NOTIFY_FAILURE": [own]})
    assert response.preconditions["SYSTEM.NOTIFY_FAILURE"] == [own]
    assert response.evidence["SYSTEM.NOTIFY_FAILURE"][own].source == "options.prior_rules"


def test_a_library_rule_this_spec_cannot_read_is_left_out_without_blaming_the_tenant(engine: Engine) -> None:
    """`OFFER: x` names nothing this spec defines; the tenant sent nothing wrong, so no warning quotes it."""
    response = _infer(engine)
    assert "'x'" not in (response.warnings.get("SYSTEM.OFFER") or "")


def test_a_source_of_another_vocabulary_does_not_apply() -> None:
    applied = LIBRARY.for_spec(["SYSTEM.GOODBYE", "SYSTEM.REQUEST", "SYSTEM.NOTIFY_FAILURE", "SYSTEM.OFFER"])
    assert [name for name, _ in applied] == ["library:Buses_9", "library:Trains_9"]
    assert LIBRARY.for_spec(["Agent.goto", "Agent.open"]) == []


def test_leaving_a_domain_out_and_the_file_format_round_trip() -> None:
    assert [s.source for s in LIBRARY.without("Buses_9").sources] == ["Trains_9", "alfworld"]
    assert from_json(to_json(LIBRARY)) == LIBRARY


def test_signed_notices_apply_to_every_spec_that_defines_them() -> None:
    """A failure notice needs a failure result in every domain: the signed rules join a spec that shares no
    vocabulary with any source, and survive a JSON round trip and leaving a domain out."""
    library = from_json(to_json(shipped())).without("Alarm_1")
    found = dict(library.for_spec(["BOT.NOTIFY_FAILURE", "BOT.Pay"]))
    assert found["library:notices"] == {"BOT.NOTIFY_FAILURE": ["not self.query_success"]}
    assert library.signed_rules("BOT.INFORM_NOTHING_FOUND") == ["self.query_success is False"]
    assert library.signed_rules("BOT.INFORM_VENUE_NOT_AVAILABLE") == ["self.query_success is False"]
    assert library.signed_rules("BOT.INFORM_BOOKING_CONFIRMED") == ["self.query_success"]
    assert library.signed_rules("BOT.ASK_CONFIRM_BOOKING") == []
    assert shipped().signed == SIGNED


def test_a_never_demonstrated_nothing_found_needs_an_empty_answer(engine: Engine) -> None:
    """No source of the library speaks this vocabulary and no demonstration shows "nothing found": the signed
    notice gives it its rule (without it: refused everywhere), refused after a success and before any search."""
    spec = SPEC.replace("  def NOTIFY_FAILURE(self): pass\n", "  def INFORM_NOTHING_FOUND(self): pass\n")
    engine.library = Library((), dict(SIGNED))
    try:
        response = engine.infer(InferRequest(spec=spec, demonstrations=DEMOS,
                                             options=InferOptions(generators=["enumerate"])))
    finally:
        engine.library = LIBRARY
    assert response.preconditions["SYSTEM.INFORM_NOTHING_FOUND"] == ["self.query_success is False"]
    evidence = response.evidence["SYSTEM.INFORM_NOTHING_FOUND"]["self.query_success is False"]
    assert (evidence.decided, evidence.source) == ("transferred", "library:notices")
