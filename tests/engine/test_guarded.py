"""Guarded actions and conversational acts: a goodbye demonstrated only after a success stays allowed without
that success; a booking keeps what it cannot rule out."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from precond.engine.engine import Engine
from precond.engine.judging.guarded import default
from precond.sandbox import Sandbox
from precond_client.schemas import InferOptions, InferRequest, InferResponse
from precond_client.schemas.errors import UnknownAction

SPEC = """from collections import defaultdict
class USER:
  def __init__(self):
    self.informed = defaultdict(lambda: False)
    self.affirmed = False
  def INFORM(self, slot): self.informed[slot] = True
  def AFFIRM(self): self.affirmed = True

class SYSTEM:
  def __init__(self, user):
    self.user, self.query_success = user, None
  def set_query_status(self, ok): self.query_success = ok
  def REQUEST(self, slot): pass
  def Book(self): pass
  def INFORM_BOOKED(self): pass
  def GOODBYE(self): pass
"""


def _dialog(goodbye: bool) -> str:
    """The goodbye right after the booking succeeded, in two dialogs: thin, and only ever after a success."""
    return "\n".join(["user = USER()", "system = SYSTEM(user)", "system.REQUEST('day')", "user.INFORM('day')",
                      "user.AFFIRM()", "system.Book()", "system.set_query_status(True)",
                      "system.GOODBYE()" if goodbye else "system.INFORM_BOOKED()"]) + "\n"


DEMOS = [_dialog(True), _dialog(True), _dialog(False), _dialog(False)]


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def _infer(engine: Engine, **options: Any) -> InferResponse:
    return engine.infer(InferRequest(spec=SPEC, demonstrations=DEMOS,
                                     options=InferOptions(generators=["enumerate"], library=False, **options)))


def test_the_default_guards_everything_but_the_conversational_acts() -> None:
    actions = ["SYSTEM.REQUEST", "SYSTEM.Book", "SYSTEM.INFORM_BOOKED", "SYSTEM.GOODBYE", "SYSTEM.REQ_MORE",
               "SYSTEM.OUT_OF_SCOPE", "SYSTEM.ANYTHING_ELSE", "SYSTEM.BLOCK_CARD", "Agent.take"]
    assert default(actions) == ["SYSTEM.REQUEST", "SYSTEM.Book", "SYSTEM.INFORM_BOOKED", "SYSTEM.BLOCK_CARD",
                                "Agent.take"]


def test_a_goodbye_seen_only_after_success_stays_allowed_without_it_and_says_so(engine: Engine) -> None:
    response = _infer(engine)
    assert "self.query_success" not in response.preconditions["SYSTEM.GOODBYE"]
    warning = response.warnings["SYSTEM.GOODBYE"]
    assert "conversational act" in warning and "self.query_success" in warning
    assert "options.guarded not given" in warning and "Book" in warning


def test_guarded_it_keeps_the_correlate_as_assumed(engine: Engine) -> None:
    response = _infer(engine, guarded=["SYSTEM.GOODBYE", "SYSTEM.Book"])
    assert "self.query_success" in response.preconditions["SYSTEM.GOODBYE"]
    assert response.evidence["SYSTEM.GOODBYE"]["self.query_success"].decided == "assumed"
    assert "options.guarded not given" not in response.warnings["SYSTEM.GOODBYE"]


def test_a_guarded_action_the_spec_does_not_define_is_refused_naming_it(engine: Engine) -> None:
    """An unknown action is the API's 422 (`unknown_action`), naming the field and the action."""
    with pytest.raises(UnknownAction) as caught:
        _infer(engine, guarded=["SYSTEM.Book", "SYSTEM.CancelBooking"])
    assert caught.value.field == "options.guarded[1]" and "CancelBooking" in caught.value.message


FAILURE_SPEC = SPEC.replace("  def GOODBYE(self): pass\n",
                            "  def GOODBYE(self): pass\n  def NOTIFY_FAILURE(self): pass\n")


def _booking(ok: bool) -> str:
    return "\n".join(["user = USER()", "system = SYSTEM(user)", "system.REQUEST('day')", "user.INFORM('day')",
                      "user.AFFIRM()", "system.Book()", f"system.set_query_status({ok})",
                      "system.INFORM_BOOKED()" if ok else "system.NOTIFY_FAILURE()"]) + "\n"


def test_a_failure_notice_demonstrated_twice_is_refused_after_success(engine: Engine) -> None:
    demos = [_booking(False), _booking(False), _booking(True), _booking(True), _booking(True)]
    response = engine.infer(InferRequest(spec=FAILURE_SPEC, demonstrations=demos, options=InferOptions(
        generators=["enumerate"], library=False)))
    rules = response.preconditions["SYSTEM.NOTIFY_FAILURE"]
    assert "not self.query_success" in rules
    assert response.evidence["SYSTEM.NOTIFY_FAILURE"]["not self.query_success"].decided == "assumed"
    assert "thin evidence" in response.warnings["SYSTEM.NOTIFY_FAILURE"]


OFFER_SPEC = FAILURE_SPEC.replace("  def GOODBYE(self): pass\n",
                                  "  def GOODBYE(self): pass\n  def ANYTHING_ELSE(self): pass\n")


def _served(ok: bool) -> str:
    """A human agent's log: the booking answers, the agent reports it, offers more help and says goodbye in the
    same turn (the user's words between them not logged)."""
    return "\n".join(["user = USER()", "system = SYSTEM(user)", "system.REQUEST('day')", "user.INFORM('day')",
                      "user.AFFIRM()", "system.Book()", f"system.set_query_status({ok})",
                      "system.INFORM_BOOKED()" if ok else "system.NOTIFY_FAILURE()", "system.ANYTHING_ELSE()",
                      "system.GOODBYE()"]) + "\n"


def test_anything_else_keeps_that_a_request_was_answered_and_a_goodbye_keeps_nothing(engine: Engine) -> None:
    """"Anything else?" follows a served request, whatever its answer: refused before anything was asked, allowed
    after a failure; the goodbye beside it answers the user, at any time."""
    demos = [_served(True), _served(True), _served(False), _served(True)]
    response = engine.infer(InferRequest(spec=OFFER_SPEC, demonstrations=demos, options=InferOptions(
        generators=["enumerate"], library=False)))
    assert response.preconditions["SYSTEM.ANYTHING_ELSE"] == ["self.query_success is not None"]
    assert response.preconditions["SYSTEM.GOODBYE"] == []


def test_anything_else_seen_only_after_success_is_not_refused_after_a_failure(engine: Engine) -> None:
    demos = [_served(True)] * 4
    response = engine.infer(InferRequest(spec=OFFER_SPEC, demonstrations=demos, options=InferOptions(
        generators=["enumerate"], library=False)))
    assert response.preconditions["SYSTEM.ANYTHING_ELSE"] == ["self.query_success is not None"]


def test_a_failure_notice_seen_only_after_failures_is_refused_after_a_success(engine: Engine) -> None:
    """Every notice followed a failure, so "an answer came" (`is not None`) is its narrowest trigger; it would
    allow the notice after a success. The failure itself is what it reports; the goodbye keeps neither."""
    demos = [_served(False).replace("system.ANYTHING_ELSE()\n", "")] * 4 + [_booking(True)] * 2
    response = engine.infer(InferRequest(spec=OFFER_SPEC, demonstrations=demos, options=InferOptions(
        generators=["enumerate"], library=False)))
    assert response.preconditions["SYSTEM.NOTIFY_FAILURE"] == ["not self.query_success"]
    assert response.preconditions["SYSTEM.INFORM_BOOKED"] == ["self.query_success"]
    assert response.preconditions["SYSTEM.GOODBYE"] == []
