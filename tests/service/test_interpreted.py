"""What the gateway judges itself and what it leaves to the sandbox. A spec is a converter's only by its structure:
one that looks like it but is not (an extra method, code in a body, a decorator, a default, one character off the
OpenAI converter's text) is judged in the sandbox, never by the interpreter; so is a history or a call outside the
forms a converter writes, and a rule outside the interpreter's grammar. A rule the service refuses is still the
same 422."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from precond.convert import sgd
from precond.gateway import interpreted, offload
from precond.gateway.converted_spec import OpenAISpec, SGDSpec, converted_spec
from precond.gateway.routes.operations import screened_check
from precond.programs import checks
from precond_client.openai_log import Tool, spec_program
from precond_client.schemas import CheckRequest

EXAMPLE = json.loads((Path(__file__).resolve().parents[2] / "examples" / "check-actions.json").read_text())
SPEC: str = EXAMPLE["spec"]
OPENAI_SPEC = spec_program([Tool("cancel_reservation", ("reservation_id",), frozenset({"reservation_id"}))],
                           {"cancel_reservation"})


def outcome(body: dict[str, Any], tag: str = "tenant") -> Any:
    return offload.screened_check(body["spec"], body.get("preconditions", {}), body.get("decided", {}),
                                  body["history"], body["calls"], tag, 1_000_000)


def with_spec(spec: str) -> dict[str, Any]:
    return {**EXAMPLE, "spec": spec}


def test_the_example_is_judged_in_the_gateway() -> None:
    judged = outcome(EXAMPLE)
    assert isinstance(judged, offload.Judged) and judged.answer["judged_by"] == "interpreter"
    assert [v["allowed"] for v in judged.answer["results"]] == [False, False]
    assert judged.answer["results"][0]["violations"] == ["self.user.informed_slot['cuisine']"]


def test_the_converters_specs_are_recognised() -> None:
    written = sgd.spec_program(sgd.Service("Cafe_1", ["FindCafe", "OrderCoffee"], ["city"]))
    assert isinstance(converted_spec(written, "t"), SGDSpec)
    assert isinstance(converted_spec(SPEC, "t"), SGDSpec)  # its methods in another order
    assert isinstance(converted_spec(OPENAI_SPEC, "t"), OpenAISpec)
    another_intent = SPEC.replace("  def REQ_MORE(self): pass\n", "  def REQ_MORE(self): pass\n  def Pay(self): pass\n")
    assert isinstance(converted_spec(another_intent, "t"), SGDSpec)  # what the converter writes for one more intent


LOOKALIKES = {
    "an extra method": SPEC.replace("  def REQ_MORE(self): pass\n",
                                    "  def REQ_MORE(self): pass\n  def steal(self, what): pass\n"),
    "an extra observation": SPEC.replace("  def NEGATE(self): self.affirmed = False\n",
                                         "  def NEGATE(self): self.affirmed = False\n"
                                         "  def WAIT(self): self.affirmed = False\n"),
    "code in a stub": SPEC.replace("  def REQ_MORE(self): pass\n",
                                   "  def REQ_MORE(self): __import__('os').system('touch /tmp/pwned')\n"),
    "a stub with an effect": SPEC.replace("  def GOODBYE(self): pass\n",
                                          "  def GOODBYE(self): self.user.no_more = True\n"),
    "code in an observation": SPEC.replace("  def INFORM(self, slot): self.informed_slot[slot] = True\n",
                                           "  def INFORM(self, slot): self.informed_slot[slot] = open('/etc/passwd')"
                                           ".read()\n"),
    "another state": SPEC.replace("    self.query_success = None\n", "    self.query_success = 1\n"),
    "a decorator": SPEC.replace("  def REQ_MORE(self): pass\n", "  @staticmethod\n  def REQ_MORE(self): pass\n"),
    "a default": SPEC.replace("  def REQUEST(self, slot): pass\n", "  def REQUEST(self, slot=print('x')): pass\n"),
    "another parameter": SPEC.replace("  def REQUEST(self, slot): pass\n", "  def REQUEST(self, intent): pass\n"),
    "a missing act": SPEC.replace("  def REQ_MORE(self): pass\n", ""),
    "a module statement": SPEC + "import os\n",
    "a base class": SPEC.replace("class SYSTEM:", "class SYSTEM(dict):"),
    "a dunder method": SPEC.replace("  def REQ_MORE(self): pass\n",
                                    "  def REQ_MORE(self): pass\n  def __eq__(self): pass\n"),
    "an OpenAI spec one line off": OPENAI_SPEC.replace("      self.changes[tool][key] = value\n",
                                                       "      self.changes[tool][key] = print(value)\n"),
}


@pytest.mark.parametrize("shape", sorted(LOOKALIKES))
def test_a_spec_that_only_looks_like_a_converters_goes_to_the_sandbox(shape: str) -> None:
    spec = LOOKALIKES[shape]
    assert spec not in (SPEC, OPENAI_SPEC)
    assert converted_spec(spec, "t") is None
    body = with_spec(spec)
    if "OpenAI" in shape:
        body = {"spec": spec, "preconditions": {"AGENT.cancel_reservation": ["reservation_id != 'x'"]},
                "history": [{"role": "user", "content": "hi"}],
                "calls": [{"name": "cancel_reservation", "arguments": {"reservation_id": "R1"}}]}
    found = outcome(body)
    assert isinstance(found, checks.Problem | offload.Queued), found


HISTORIES = {
    "an assignment": "x = 1\n",
    "a loop": "for s in ['a']:\n  user.INFORM(s)\n",
    "a write to the state": "user.informed_slot['cuisine'] = True\n",
    "a keyword argument": "user.INFORM(slot='cuisine')\n",
    "a list argument": "user.INFORM(['cuisine'])\n",
    "a call of a name": "print('x')\n",
    "a new object": "other = USER()\nother.INFORM('cuisine')\n",  # allowed: a second USER is a converter form
}


@pytest.mark.parametrize("form", sorted(HISTORIES))
def test_a_history_outside_the_converters_forms_goes_to_the_sandbox(form: str) -> None:
    body = {**EXAMPLE, "history": EXAMPLE["history"] + HISTORIES[form]}
    found = outcome(body)
    if isinstance(found, checks.Problem):
        return  # refused by the screen, as before
    assert isinstance(found, offload.Judged if form == "a new object" else offload.Queued), found


@pytest.mark.parametrize("call", ["system.REQUEST(slot='city')", "system.REQUEST(['city'])", "user.INFORM('city')",
                                  "system.set_query_status(True)", "system.REQUEST('a', 'b')"])
def test_a_call_outside_the_converters_forms_goes_to_the_sandbox(call: str) -> None:
    found = outcome({**EXAMPLE, "calls": [call]})
    assert isinstance(found, checks.Problem | offload.Queued), found


@pytest.mark.parametrize("rule", ["str(slot) != 'x'", "getattr(self, 'query_success')", "self.user.__class__",
                                  "[x for x in self.user.informed_slot]", "self.user.informed_slot"])
def test_a_rule_outside_the_interpreters_grammar_goes_to_the_sandbox_or_is_refused(rule: str) -> None:
    found = outcome({**EXAMPLE, "preconditions": {"SYSTEM.INFORM": [rule]}})
    assert isinstance(found, checks.Problem | offload.Queued), found


def test_a_rule_the_service_refuses_is_the_same_422() -> None:
    found = outcome({**EXAMPLE, "preconditions": {"SYSTEM.INFORM": ["assert slot"]}})
    assert isinstance(found, checks.Problem) and found.field.startswith("preconditions"), found
    unknown = outcome({**EXAMPLE, "preconditions": {"SYSTEM.INFROM": ["True"]}})
    assert isinstance(unknown, checks.Problem) and unknown.type == checks.UNKNOWN_ACTION, unknown


def test_rules_on_an_observation_go_to_the_sandbox() -> None:
    found = outcome({**EXAMPLE, "preconditions": {"SYSTEM.set_query_status": ["status is True"]}})
    assert isinstance(found, checks.Problem | offload.Queued), found


def test_what_is_compiled_is_remembered_per_tenant_and_bounded() -> None:
    before = len(interpreted._REMEMBERED.sets)
    for n in range(interpreted.REMEMBERED_SETS + 5):
        outcome(EXAMPLE, tag=f"tenant-{n}")
    assert len(interpreted._REMEMBERED.sets) == interpreted.REMEMBERED_SETS >= before


class CountingPool:
    """The check pool's `run` as the route calls it, done here, with the work it was told."""

    def __init__(self) -> None:
        self.chars: list[int] = []

    async def run(self, tag: str, chars: int, function: Any, *args: Any) -> Any:
        self.chars.append(chars)
        return function(*args)


def test_a_rule_that_iterates_is_judged_in_the_pool_never_on_the_loop() -> None:
    heavy = "all(c != 'x' for c in slot * 100000)"  # 200,000 steps at most: far too long for the event loop
    pool = CountingPool()
    services = SimpleNamespace(checks=pool, settings=SimpleNamespace(interpret_checks=True))
    for rules in (EXAMPLE["preconditions"], {"SYSTEM.INFORM": [heavy]}):
        body = CheckRequest.model_validate({**EXAMPLE, "preconditions": rules})
        found = asyncio.run(screened_check(services, "tenant", body))  # type: ignore[arg-type]
        assert not isinstance(found, checks.Problem), found
    light, iterating = pool.chars
    assert light <= offload.INLINE_CHARS < iterating
    # past the interpreter's step budget, the sandbox judges it (under its CPU limit): never a refusal of its own
    assert isinstance(found, offload.Queued), found


def test_a_look_alike_specs_code_is_never_run_here(tmp_path: Path) -> None:
    """Every place a body could hide code, each writing a canary file if it ran: the gateway sends the check to
    the sandbox (or refuses it) and runs none of it itself."""
    canary = tmp_path / "ran"
    code = f"open({str(canary)!r}, 'w').write('x')"
    specs = [SPEC.replace("  def REQ_MORE(self): pass\n", f"  def REQ_MORE(self): {code}\n"),
             SPEC.replace("  def GOODBYE(self): pass\n", f"  def GOODBYE(self): pass\n  {code}\n"),
             SPEC.replace("    self.query_success = None\n", f"    self.query_success = {code}\n"),
             SPEC + code + "\n"]
    bodies = [with_spec(spec) for spec in specs] + [
        {**EXAMPLE, "history": EXAMPLE["history"] + code + "\n"},
        {**EXAMPLE, "calls": [f"system.REQUEST({code})"]},
        {**EXAMPLE, "preconditions": {"SYSTEM.INFORM": [code]}}]
    for body in bodies:
        found = outcome(body, tag=f"canary-{len(str(body))}")
        assert isinstance(found, checks.Problem | offload.Queued), found
    assert not canary.exists()
