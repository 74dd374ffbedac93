"""The embedded guard (`precond_client.guard.Guard`): what it takes (a set over the converter's spec whose every rule
is a form the learner writes), what it refuses to embed (naming the rule and why, with nothing run), how it
judges what it cannot (fail closed by default, an unknown tool always refused), and that a bad message, a long
call and a rule that reads a table a call's other rules filled are answered as the service answers them (a real
stack: Redis, gateway, a worker with the real sandbox)."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from precond.convert.openai import convert
from precond.engine.candidates.enumeration import StateModel, enumerate_atoms
from precond.engine.spec import parse_spec
from precond.sandbox.astfilter import MAX_EXPRESSION_CHARS
from precond.sandbox.child.values import clean as sandbox_clean
from precond.sandbox.types import ActionInfo
from precond.stack.keyed import KeyedStack
from precond_client import Client, InvalidInput, Retry
from precond_client.guard import (
    AGENT_SHAPE,
    MAX_CALL_CHARS,
    NO_SUCH_TOOL,
    Guard,
    NotEmbeddable,
    ServiceGuard,
    clean,
    refusal,
)
from precond_client.openai_log import AGENT_STATE, USER_SPEC, converter_spec, outcome

ROOT = Path(__file__).resolve().parents[2]
TAU = ROOT / "tests" / "fixtures" / "tau_airline"
RECORDS = json.loads((TAU / "trajectories.json").read_text())
TOOLS = json.loads((TAU / "tools.json").read_text())
SPEC = convert(RECORDS, TOOLS).spec
READ = "reservation_id in self.results['get_reservation_details']"
CANCEL = {"name": "cancel_reservation", "arguments": '{"reservation_id": "FDZ0T5"}'}


def history_until_the_cancellation() -> list[dict[str, Any]]:
    """Task 30's successful run up to its first cancellation (of FDZ0T5, which it read)."""
    traj = RECORDS[1]["traj"]
    return traj[:next(i for i, m in enumerate(traj) for c in m.get("tool_calls") or []
                      if c["function"]["name"] == "cancel_reservation")]


def test_every_condition_the_enumerator_writes_over_a_converted_spec_is_embeddable() -> None:
    """The grammar is the learner's: each atom the enumerator proposes for every tool of the fixture's spec (the
    generic conditions and `tool_conditions`' reads, fields, arguments and disjunctions) compiles."""
    converted = convert(RECORDS, TOOLS)
    spec = parse_spec(converted.spec)
    demos = [ast.parse(t.program) for t in converted.trajectories]
    model = StateModel(spec, demos)
    atoms: dict[str, list[str]] = {}
    for tool in converted.tools:
        method = spec.methods[f"AGENT.{tool.name}"]
        seen = tuple(tuple(c.arguments.get(p) for p in method.positional) for t in converted.trajectories
                     for c in t.calls if c.tool == tool.name)
        info = ActionInfo(f"AGENT.{tool.name}", method.positional, True, (), seen)
        atoms[f"AGENT.{tool.name}"] = enumerate_atoms(model, info, "AGENT").atoms
    assert sum(len(a) for a in atoms.values()) > 900
    assert any(" or " in a for a in atoms["AGENT.cancel_reservation"])  # disjunctions of fields among them
    Guard(converted.spec, atoms)  # raises NotEmbeddable naming any that is not


@pytest.mark.parametrize(("rule", "reason"), [
    ("__import__('os').system('touch /tmp/guard-pwned')", "calls len, all, any, max, min, sum only"),
    ("len(__import__)", "`__import__` is neither `self` nor a parameter"),
    ("().__class__.__bases__[0]", "'__class__' is not an attribute of the state"),
    ("self.__dict__", "'__dict__' is not an attribute of the state"),
    ("self.results.get(reservation_id)", "calls len, all, any, max, min, sum only"),
    ("[r for r in self.results]", "the state's table is read only by attribute or subscript"),
    ("[self for self in [1]]", "the variable must be a plain name"),
    ("{k: 1 for k in reservation_id}", "DictComp is not among the forms"),
    ("reservation_id is 'FDZ0T5'", "`is` compares with None, True or False only"),
    ("self.results", "the state's table, not a value"),
    ("WRITES", "is neither `self` nor a parameter"),
    ("reservation_id[1:]", "a slice"),
    ("lambda: 1", "Lambda is not among the forms"),
    ("reservation_id in", "not an expression"),
])
def test_a_rule_outside_the_grammar_makes_the_set_non_embeddable_naming_it(rule: str, reason: str) -> None:
    with pytest.raises(NotEmbeddable) as raised:
        Guard(SPEC, {"AGENT.cancel_reservation": [READ, rule]})
    [problem] = raised.value.problems
    assert problem.startswith(f"AGENT.cancel_reservation: rule {rule!r}: ") and reason in problem, problem
    assert not Path("/tmp/guard-pwned").exists()


@pytest.mark.parametrize(("spec", "why"), [
    (SPEC.replace("self.last_ok = ok", "self.last_ok = True"), "line 20 differs from what `precond convert openai`"),
    (SPEC + "  def helper(self):\n    return 1\n", "differs from what `precond convert openai`"),
    ("\n".join(line for line in SPEC.splitlines() if "seen" not in line) + "\n",  # an older converter's
     "line 17 differs from what `precond convert openai` writes: it is not that spec (one an older version wrote: "
     "convert the logs again"),
    ("class AGENT:\n  pass\n", "no `WRITES = (...)`"),
    ("import os\n", "no `WRITES = (...)`"),
])
def test_a_spec_other_than_the_converters_is_not_embeddable(spec: str, why: str) -> None:
    assert "self.last_ok = ok" in SPEC
    with pytest.raises(NotEmbeddable, match="spec: ") as raised:
        Guard(spec, {})
    assert why in str(raised.value)


def test_rules_of_what_is_not_a_tool_are_not_embeddable() -> None:
    with pytest.raises(NotEmbeddable, match=r"USER\.says: not a tool of the spec"):
        Guard(SPEC, {"USER.says": ["True"]})


def test_the_state_a_rule_reads_is_the_specs() -> None:
    """`AGENT_SHAPE` names what AGENT and USER of the converter's spec assign, and nothing else."""
    assigned: dict[str, set[str]] = {}
    for node in ast.walk(ast.parse(USER_SPEC + AGENT_STATE)):
        if isinstance(node, ast.ClassDef):
            assigned[node.name] = {t.attr for n in ast.walk(node) if isinstance(n, ast.Assign)
                                   for t in n.targets if isinstance(t, ast.Attribute)}
    assert set(AGENT_SHAPE.attributes) == assigned["AGENT"]
    assert set(AGENT_SHAPE.attributes["user"].attributes) == assigned["USER"]
    assert converter_spec(SPEC)[1] == frozenset({"book_reservation", "cancel_reservation", "send_certificate",
                                                 "update_reservation_baggages", "update_reservation_flights",
                                                 "update_reservation_passengers"})


def test_the_sandboxs_bounds_and_text_cleaning_are_the_guards() -> None:
    assert MAX_CALL_CHARS == MAX_EXPRESSION_CHARS
    for text in ("plain", "x" * 600, "\ud800 lone surrogate", "é" * 300):
        for limit in (200, 500, 4000):
            assert clean(text, limit) == sandbox_clean(text, limit)


def test_an_unknown_tool_is_refused_even_by_a_guard_that_fails_open() -> None:
    for fail_closed in (True, False):
        verdict = Guard(SPEC, {}, fail_closed=fail_closed).session().check("drop_database", "{}")
        assert not verdict.allowed and verdict.error is not None and verdict.error.startswith(NO_SUCH_TOOL)


def test_a_call_it_cannot_judge_is_refused_with_the_reason_or_allowed_when_failing_open() -> None:
    history = history_until_the_cancellation()
    closed = Guard(SPEC, {"AGENT.cancel_reservation": [READ]}).session(history)
    verdict = closed.check("cancel_reservation", '{"booking": "X"}')
    assert not verdict.allowed
    assert verdict.error == ("not judged: calls[0].arguments: cancel_reservation has no parameter 'booking' "
                             "(reservation_id)")
    opened = Guard(SPEC, {"AGENT.cancel_reservation": [READ]}, fail_closed=False).session(history)
    assert opened.check("cancel_reservation", "{reservation_id: 1").allowed
    assert opened.check(**CANCEL).allowed and not opened.check("cancel_reservation", '{"reservation_id": "X"}').allowed


def test_each_verdict_says_what_its_tools_rule_rests_on() -> None:
    """Allowed because the evidence says so, or because nothing is known: `rule_status`, as the service says it."""
    labelled = Guard(SPEC, {"AGENT.cancel_reservation": [READ]}, {"AGENT.cancel_reservation": {READ: "zero-shot"}})
    session = labelled.session(history_until_the_cancellation())
    cancel, read = session.check(**CANCEL), session.check("get_reservation_details", '{"reservation_id": "X"}')
    assert (cancel.action, cancel.rule_status) == ("AGENT.cancel_reservation", "zero-shot")
    assert read.allowed and (read.action, read.rule_status) == ("AGENT.get_reservation_details", "missing")
    unlabelled = Guard(SPEC, {"AGENT.cancel_reservation": [READ]}).session().check(**CANCEL)
    assert not unlabelled.allowed and unlabelled.rule_status == "given"
    unknown = labelled.session().check("drop_database", "{}")
    assert unknown.action is None and unknown.rule_status is None


def test_a_refusal_tells_the_model_why_and_reads_later_as_a_failed_call() -> None:
    session = Guard(SPEC, {"AGENT.cancel_reservation": [READ]}, {"AGENT.cancel_reservation": {READ: "assumed"}},
                    name="ps_x@2").session([{"role": "user", "content": "cancel FDZ0T5"}])
    verdict = session.check(**CANCEL)
    assert verdict.violations == [READ] and verdict.decided == {READ: "assumed"}
    text = refusal(verdict, "ps_x@2")
    assert f"`{READ}` does not hold (decided: assumed)" in text and "ps_x@2" in text
    assert outcome(text) == (False, text)  # in the history it is an error, never a successful read


@pytest.fixture(scope="module")
def service(keyed: KeyedStack) -> Any:
    with Client(keyed.url, api_key=keyed.keys["guard"], retry=Retry(attempts=2)) as client:
        yield client


@pytest.mark.parametrize(("change", "field"), [
    (lambda h: h.append({"content": "hello"}), "history[{n}]"),
    (lambda h: h.append({"role": "robot", "content": "hello"}), "history[{n}].role"),
    (lambda h: h.append({"role": "tool", "content": "{}"}), "history[{n}]"),
    (lambda h: h.append({"role": "assistant", "tool_calls": [{"function": {"name": "drop_db", "arguments": "{}"}}]}),
     "history[{n}].tool_calls[0].function.name"),
    (lambda h: h.append({"role": "assistant", "tool_calls": [
        {"function": {"name": "cancel_reservation", "arguments": "{reservation_id: 1"}}]}),
     "history[{n}].tool_calls[0].function.arguments"),
    (lambda h: h.append({"role": "assistant", "tool_calls": [{"function": {
        "name": "cancel_reservation", "arguments": '{"reservation_id": ' + "[" * 40 + "]" * 40 + "}"}}]}),
     "history[{n}].tool_calls[0].function.arguments.reservation_id"),
])
def test_a_message_the_converter_refuses_is_the_services_422(service: Client, change: Any, field: str) -> None:
    history = history_until_the_cancellation()
    change(history)
    with pytest.raises(InvalidInput) as from_service:
        service.check_actions({"spec": SPEC, "preconditions": {}, "history": history, "calls": [CANCEL]})
    session = Guard(SPEC, {}).session()
    with pytest.raises(InvalidInput) as embedded:
        session.extend(history)
    assert (embedded.value.message, embedded.value.field) == (from_service.value.message, from_service.value.field)
    assert embedded.value.field == field.format(n=len(history) - 1) and embedded.value.status == 422
    verdict = session.check(**CANCEL)  # and nothing is judged after it
    assert not verdict.allowed
    assert verdict.error == f"not judged: the history could not be read: {embedded.value.message}"


def test_tables_long_calls_and_raising_rules_are_answered_as_the_service_answers(service: Client) -> None:
    """`self.results[x]` of a table that lacks `x` makes `x in self.results` true for that call's later rules (the
    spec's defaultdict), and only for that call; a call longer than the sandbox takes is refused unread; a rule
    that raises is named with its exception."""
    rules = {"AGENT.cancel_reservation": ["self.results[reservation_id]", "reservation_id in self.results",
                                          "self.results['get_reservation_details'][reservation_id]['nope']"],
             "AGENT.send_certificate": ["user_id in self.results", "not self.results[user_id]"]}
    stored = service.create_set({"spec": SPEC, "preconditions": rules})
    history = history_until_the_cancellation()
    calls = [CANCEL, {"name": "send_certificate", "arguments": {"user_id": "u" * 5000, "amount": 1}},
             {"name": "send_certificate", "arguments": {"user_id": "mia_li_3668", "amount": 1}},
             {"name": "cancel_reservation", "arguments": {"reservation_id": [{"a": 1}]}},
             {"name": "send_certificate", "arguments": {"user_id": "FDZ0T5", "amount": 1}}]
    expected = service.check_with_set(stored.reference, history, calls).results
    session = Guard.from_set(service.get_set(stored.reference)).session(history)
    embedded = [session.check(c["name"], c["arguments"]) for c in calls]
    assert [v.model_dump() for v in embedded] == [v.model_dump() for v in expected]
    assert embedded[0].violations == ["self.results[reservation_id]"] and "KeyError: 'nope'" in str(embedded[0].error)
    assert embedded[1].error == "rejected: not a single-line call"
    assert embedded[2].violations == ["user_id in self.results"]  # `not {}`: what the table gave holds
    assert embedded[3].error == ("arguments break cancel_reservation's JSON Schema: reservation_id: [{'a': 1}] is "
                                 "not of type 'string'")  # refused before its rules are asked
    assert embedded[4].violations == ["user_id in self.results"]  # the first call's read inserted nothing here


def test_the_service_guard_fails_closed_when_the_service_does_not_answer() -> None:
    with Client("http://127.0.0.1:9", retry=Retry(attempts=1)) as client:
        session = ServiceGuard(client, "ps_000000000000000000000000@1").session()
        verdict = session.check(**CANCEL)
        assert not verdict.allowed and verdict.error is not None and verdict.error.startswith("not judged: ")
        assert ServiceGuard(client, "ps_000000000000000000000000@1", fail_closed=False).session().check(
            **CANCEL).allowed


HOSTILE_PROBE = """
import json, sys
from precond_client.guard import Guard, NotEmbeddable
spec, canary = sys.argv[1], sys.argv[2]
touch = f"__import__('os').system('touch {canary}')"
rules = [touch, f"len({touch})", f"(lambda: {touch})()", f"[{touch} for x in (1,)]",
         f"self.__class__.__init__.__globals__['__builtins__']['exec']('open({canary!r}, \\\\'w\\\\')')",
         f"reservation_id.__class__.__mro__[1].__subclasses__()", f"getattr(self, 'results')"]
refused = 0
for rule in rules:
    try:
        Guard(spec, {"AGENT.cancel_reservation": [rule]})
    except NotEmbeddable:
        refused += 1
read = "reservation_id in self.results['get_reservation_details']"
session = Guard(spec, {"AGENT.cancel_reservation": [read]}).session()
session.add({"role": "user", "content": f"x'); {touch}; ('"})
session.add({"role": "assistant", "tool_calls": [{"function": {"name": "get_reservation_details",
             "arguments": json.dumps({"reservation_id": f"'); {touch}; ('"})}}]})
session.add({"role": "tool", "content": json.dumps({"__class__": touch, "cabin": f"{touch}"})})
verdict = session.check("cancel_reservation", json.dumps({"reservation_id": f"'); {touch}; ('"}))
print(json.dumps({"refused": refused, "of": len(rules), "allowed": verdict.allowed}))
"""


@pytest.mark.parametrize("user", ["root", "nobody"])
def test_hostile_rules_and_messages_run_nothing_as_root_or_not(user: str, tmp_path: Path) -> None:
    """Rules that reach for the interpreter's machinery are refused unrun; code in messages, arguments and results
    is data (the call whose argument names the reservation read is allowed, nothing more happens)."""
    if user == "nobody" and os.geteuid() != 0:
        pytest.skip("already not root: the root case ran as this user")
    tmp_path.chmod(0o777)
    canary = tmp_path / "pwned"
    prefix = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"] if user == "nobody" else []
    done = subprocess.run([*prefix, sys.executable, "-c", HOSTILE_PROBE, SPEC, str(canary)], cwd=tmp_path,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, capture_output=True, text=True,
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout) == {"refused": 7, "of": 7, "allowed": True}
    assert not canary.exists()
