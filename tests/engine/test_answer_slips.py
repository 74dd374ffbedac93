"""A human agent's failure notice, once sent after a success: the notice keeps the failure as its rule, with
that call as its exception (`options.answer_slips`), instead of "an answer came", which allows it after a
success."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from pydantic import ValidationError

from precond.engine.engine import Engine
from precond.sandbox import Sandbox
from precond_client.schemas import InferOptions, InferRequest, InferResponse

SPEC = """from collections import defaultdict
class USER:
  def __init__(self):
    self.informed = defaultdict(lambda: False)
  def INFORM(self, slot): self.informed[slot] = True

class SYSTEM:
  def __init__(self, user):
    self.user, self.query_success = user, None
  def set_query_status(self, ok): self.query_success = ok
  def REQUEST(self, slot): pass
  def Reserve(self): pass
  def INFORM_RESERVED(self): pass
  def INFORM_RESERVATION_FAILED(self): pass
"""


def _dialog(ok: bool, notice: str) -> str:
    return "\n".join(["user = USER()", "system = SYSTEM(user)", "system.REQUEST('flight')", "user.INFORM('flight')",
                      "system.Reserve()", f"system.set_query_status({ok})", f"system.{notice}()"]) + "\n"


FAILED, RESERVED = "INFORM_RESERVATION_FAILED", "INFORM_RESERVED"
DEMOS = [_dialog(False, FAILED), _dialog(False, FAILED), _dialog(True, FAILED), _dialog(False, FAILED),
         _dialog(True, RESERVED), _dialog(True, RESERVED), _dialog(True, RESERVED)]
"""Four failure notices, the third after a success (the agent's slip)."""


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def _infer(engine: Engine, **options: Any) -> InferResponse:
    return engine.infer(InferRequest(spec=SPEC, demonstrations=DEMOS, options=InferOptions(
        generators=["enumerate"], library=False, **options)))


def test_the_notice_sent_once_after_a_success_keeps_the_failure_and_names_that_call(engine: Engine) -> None:
    response = _infer(engine)
    assert response.preconditions[f"SYSTEM.{FAILED}"] == ["not self.query_success"]
    kept = response.evidence[f"SYSTEM.{FAILED}"]["not self.query_success"]
    assert (kept.occurrences, kept.holds) == (4, 3)
    assert [(e.demonstration, e.call) for e in kept.exceptions] == [(2, f"system.{FAILED}()")]


def test_without_answer_slips_it_keeps_only_that_an_answer_came(engine: Engine) -> None:
    response = _infer(engine, answer_slips=0.0)
    assert response.preconditions[f"SYSTEM.{FAILED}"] == ["self.query_success is not None"]


def test_two_slips_in_four_calls_are_not_slips(engine: Engine) -> None:
    demos = [*DEMOS[:3], _dialog(True, FAILED), *DEMOS[4:]]
    response = engine.infer(InferRequest(spec=SPEC, demonstrations=demos, options=InferOptions(
        generators=["enumerate"], library=False)))
    assert "not self.query_success" not in response.preconditions[f"SYSTEM.{FAILED}"]


def test_a_prior_that_a_notice_needs_an_answer_is_read_for_the_value_its_calls_show(engine: Engine) -> None:
    """Another service guessed `is not None` for its never-demonstrated notice; here the notice is called twice,
    each time just after a failure: the failure is the reading, kept as assumed (two calls)."""
    demos = [_dialog(False, FAILED), _dialog(False, FAILED), *DEMOS[4:]]
    response = engine.infer(InferRequest(spec=SPEC, demonstrations=demos, options=InferOptions(
        generators=["enumerate"], library=False,
        prior_rules={f"SYSTEM.{FAILED}": ["self.query_success is not None"]})))
    assert response.preconditions[f"SYSTEM.{FAILED}"] == ["not self.query_success"]
    assert response.evidence[f"SYSTEM.{FAILED}"]["not self.query_success"].decided == "assumed"


@pytest.mark.parametrize("value", [-0.01, 0.51, "often", None, float("nan")])
def test_answer_slips_outside_0_to_half_or_not_a_number_is_refused_naming_it(value: object) -> None:
    with pytest.raises(ValidationError) as caught:
        InferOptions.model_validate({"answer_slips": value})
    assert caught.value.errors()[0]["loc"] == ("answer_slips",)
