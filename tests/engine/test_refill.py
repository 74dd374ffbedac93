"""A refill assistant written for these tests: the patient's "yes" comes right before every refill, so it explains
every demonstrated call; what makes a refill allowed hides behind it (refills left, or the doctor's approval)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from precond.engine.candidates.library import Library
from precond.engine.engine import Engine
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferOptions, InferRequest, InferResponse

SPEC = """class PATIENT:
  def __init__(self):
    self.asked = False
    self.said_yes = False
  def ASK_REFILL(self): self.asked = True
  def YES(self): self.said_yes = True

class PHARMACY:
  def __init__(self, patient):
    self.patient = patient
    self.has_refills = False
    self.doctor_approved = False
    self.refilled = None
  def LOOKUP(self): pass
  def ASK_DOCTOR(self): pass
  def OFFER_REFILL(self): pass
  def REFILL(self): pass
  def SORRY(self): pass
  def lookup_result(self, refills_left): self.has_refills = refills_left > 0
  def doctor_result(self, approved): self.doctor_approved = approved
  def refill_result(self, ok): self.refilled = ok
"""
RULE = "self.has_refills or self.doctor_approved"


def _dialog(refills_left: int, doctor: bool | None) -> str:
    """The patient asks; the pharmacy looks the prescription up (and asks the doctor when none is left); it offers
    the refill, the patient says yes, and the refill follows, or an apology when nothing allows it."""
    steps = ["patient = PATIENT()", "pharmacy = PHARMACY(patient)", "patient.ASK_REFILL()", "pharmacy.LOOKUP()",
             f"pharmacy.lookup_result({refills_left})"]
    if doctor is not None:
        steps += ["pharmacy.ASK_DOCTOR()", f"pharmacy.doctor_result({doctor})"]
    steps += ["pharmacy.OFFER_REFILL()", "patient.YES()"]
    if refills_left > 0 or doctor:
        steps += ["pharmacy.REFILL()", "pharmacy.refill_result(True)"]
    else:
        steps += ["pharmacy.SORRY()"]
    return "\n".join(steps) + "\n"


REFILLED = [_dialog(2, None), _dialog(0, True), _dialog(1, None), _dialog(0, True), _dialog(3, None),
            _dialog(0, True)]
TURNED_AWAY = [_dialog(0, False), _dialog(0, False)]


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        engine = Engine(sandbox, None)
        engine.library = Library()
        yield engine


def _infer(engine: Engine, demos: list[str]) -> InferResponse:
    return engine.infer(InferRequest(spec=SPEC, demonstrations=demos,
                                     options=InferOptions(generators=["enumerate"], candidates="all")))


def _allowed(engine: Engine, rules: dict[str, list[str]], history: list[dict[str, Any]]) -> bool:
    verdict = engine.check(CheckRequest(spec=SPEC, preconditions=rules, history=history,
                                        calls=["pharmacy.REFILL()"])).results[0]
    assert verdict.error is None, verdict.error
    return verdict.allowed


def _yes_after(refills_left: int, doctor: bool | None) -> list[dict[str, Any]]:
    events = [("patient", "ASK_REFILL", []), ("pharmacy", "LOOKUP", []), ("pharmacy", "lookup_result", [refills_left])]
    if doctor is not None:
        events += [("pharmacy", "ASK_DOCTOR", []), ("pharmacy", "doctor_result", [doctor])]
    events += [("pharmacy", "OFFER_REFILL", []), ("patient", "YES", [])]
    return [{"actor": actor, "act": act, "args": args} for actor, act, args in events]


def test_a_refill_after_yes_needs_refills_left_or_the_doctors_approval(engine: Engine) -> None:
    """The demonstrations show a yes followed by an apology where neither held: the disjunction is kept."""
    response = _infer(engine, REFILLED + TURNED_AWAY)
    rules = response.preconditions
    assert RULE in rules["PHARMACY.REFILL"] and "self.patient.said_yes" in rules["PHARMACY.REFILL"]
    assert response.evidence["PHARMACY.REFILL"][RULE].decided == "assumed"
    assert not _allowed(engine, rules, _yes_after(0, None))
    assert not _allowed(engine, rules, _yes_after(0, False))
    assert _allowed(engine, rules, _yes_after(2, None))
    assert _allowed(engine, rules, _yes_after(0, True))


def test_without_a_turned_away_patient_the_back_ends_answers_still_guard_the_refill(engine: Engine) -> None:
    """Every demonstration ends in a refill, so nothing witnesses the disjunction; but its terms are what the
    pharmacy's back-end answered (refills left, the doctor's approval), which the patient's yes cannot override:
    it is kept, assumed, and a yes after a back-end no is refused."""
    response = _infer(engine, REFILLED)
    rules = response.preconditions
    assert RULE in rules["PHARMACY.REFILL"]
    assert response.evidence["PHARMACY.REFILL"][RULE].decided == "assumed"
    assert not _allowed(engine, rules, _yes_after(0, False))
    assert _allowed(engine, rules, _yes_after(0, True))
