"""A never-demonstrated guarded action assumes the conditions the other guarded actions share
(precond/engine/judging/unseen_shared.py) instead of `options.unseen`'s placeholder, only where they are shared,
name its parameters and agree with its labelled calls."""

from __future__ import annotations

from dataclasses import replace

from precond.convert.openai import convert
from precond.engine.engine import Engine
from precond.engine.judging.counterexamples import Outcome, Separation
from precond.engine.judging.ranking import Candidate
from precond.engine.judging.report import UNSEEN_RULE, Ranked
from precond.engine.judging.unseen_shared import Calls, assume_shared
from precond.engine.spec import parse_spec
from precond.sandbox import CandidateResult, Point, Sandbox
from precond_client.schemas import InferRequest

READ = "record_id in self.results['get_record']"
OK = "self.last_ok"
SPEC = parse_spec("class AGENT:\n" + "".join(
    f"    def {name}(self, record_id):\n        pass\n" for name in ("update_a", "update_b", "update_c", "update_d")))
A, B, C, D = (f"AGENT.update_{x}" for x in "abcd")


def ranked(*valid: str) -> Ranked:
    return Ranked(results=[], valid=[Candidate(e, "enumerate", 0) for e in valid], clusters=[], chosen=[])


def run(chosen: dict[str, list[str]], separated: dict[str, Separation] | None = None
        ) -> tuple[dict[str, list[str]], dict[str, Ranked]]:
    rankings = {a: ranked(READ, OK) for a in chosen}
    assume_shared(chosen, rankings, separated or {}, list(chosen), SPEC.methods, Calls({}, {}))
    return chosen, rankings


def labelled(truth: dict[str, int], positive: int, negative: int) -> dict[str, Separation]:
    outcome = Outcome(["call 0", "call 1"], truth, positive, negative, [])
    return {C: Separation(ranked(READ, OK), {}, {}, set(), [], True, outcome=outcome)}


def test_the_shared_read_of_the_named_key_is_assumed_with_a_warning() -> None:
    chosen, rankings = run({A: [READ, OK], B: [READ, OK], C: [UNSEEN_RULE]})
    assert chosen[C] == [READ]  # `self.last_ok` names no parameter: not adopted
    assert rankings[C].decided == {READ: "assumed"}
    assert "never demonstrated" in rankings[C].assumed and READ in rankings[C].assumed


def test_one_action_is_not_enough_to_share() -> None:
    chosen, _ = run({A: [READ], B: [], C: [UNSEEN_RULE]})
    assert chosen[C] == [UNSEEN_RULE]


def test_a_condition_another_able_action_does_not_keep_is_not_shared() -> None:
    chosen, _ = run({A: [READ], B: [READ], D: [OK], C: [UNSEEN_RULE]})
    assert chosen[C] == [UNSEEN_RULE]  # D could state the read and did not keep it


def test_labels_it_would_allow_wrongly_keep_the_placeholder() -> None:
    chosen, _ = run({A: [READ], B: [READ], C: [UNSEEN_RULE]}, labelled({READ: 0b11}, 0b01, 0b10))
    assert chosen[C] == [UNSEEN_RULE]  # call 1 is labelled 'refuse' and the read holds there


def test_labels_it_fits_let_it_be_assumed() -> None:
    chosen, _ = run({A: [READ], B: [READ], C: [UNSEEN_RULE]}, labelled({READ: 0b01}, 0b01, 0b10))
    assert chosen[C] == [READ]


TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {"record_id": {"type": "string"}}, "required": ["record_id"]}}}
    for name in ("get_record", "update_a", "update_b", "update_c")]


def tool_run(tool: str, record: str) -> list[dict[str, object]]:
    arguments = f'{{"record_id": "{record}"}}'
    return [{"role": "user", "content": "please"},
            {"role": "assistant", "tool_calls": [{"function": {"name": "get_record", "arguments": arguments}}]},
            {"role": "tool", "content": f'{{"record_id": "{record}", "status": "open"}}'},
            {"role": "assistant", "tool_calls": [{"function": {"name": tool, "arguments": arguments}}]},
            {"role": "tool", "content": "{}"}]


def test_an_inference_gives_the_undemonstrated_write_the_shared_read_and_says_so() -> None:
    """Two demonstrated writes each read the record they name first; the third, never demonstrated, assumes
    that read (not the conversation facts they keep too) and its warning says where it came from."""
    demos = convert([tool_run(t, f"r{i}") for i in range(4) for t in ("update_a", "update_b")], TOOLS)
    with Sandbox(workers=2) as sandbox:
        inferred = Engine(sandbox, None).infer(InferRequest.model_validate({
            "spec": demos.spec, "demonstrations": [t.program for t in demos.trajectories],
            "options": {"generators": ["enumerate"]}}))
    read = "record_id in self.results['get_record']"
    assert inferred.preconditions[C] == [read]
    assert inferred.evidence[C][read].decided == "assumed"
    assert "never demonstrated: assumed 1 condition(s)" in inferred.warnings[C]


STATUS = "self.results['get_record'][record_id] == 'open'"
POINTS = [Point(0, position, (record,)) for position in range(4) for record in ("r1", "r2")]
"""A's points: record r1 at positions 0-3 and r2 beside it; A is called on r1 at position 1."""


def with_status(holds: list[int]) -> dict[str, list[str]]:
    """A keeps the read and STATUS, which holds at A's points `holds`; B keeps the read; C is unseen."""
    chosen = {A: [READ, STATUS], B: [READ], C: [UNSEEN_RULE]}
    rankings = {a: ranked(READ, OK) for a in chosen}
    rankings[A] = replace(rankings[A], results=[CandidateResult(STATUS, "valid", None, sum(1 << b for b in holds))])
    assume_shared(chosen, rankings, {}, list(chosen), SPEC.methods, Calls({A: POINTS}, {A: [POINTS[2]]}))
    assert all(rankings[C].decided.get(e) == "assumed" for e in chosen[C] if e != UNSEEN_RULE)
    return chosen


def test_a_condition_another_action_undoes_by_its_call_keeps_the_placeholder() -> None:
    """A asks that the record be open and closes it: C, never demonstrated, may be the one that reopens it."""
    assert with_status([0, 1, 2, 3]) == {A: [READ, STATUS], B: [READ], C: [UNSEEN_RULE]}  # fails for r1 after


def test_a_condition_the_action_keeps_without_undoing_it_does_not_stop_the_shared_read() -> None:
    assert with_status([0, 1, 2, 3, 4, 5, 6, 7])[C] == [READ]  # A's clause stays true after its call: a policy


ROOM = """from collections import defaultdict
class Env:
  def __init__(self):
    self.state = defaultdict(lambda: False)
  def set_property(self, obj, prop, value):
    self.state[(obj, prop)] = value
  def get_property(self, obj, prop):
    return self.state[(obj, prop)]
class Agent:
  def __init__(self, env):
    self.env = env
    self.seen = set()
  def look(self, *objs): self.seen.update(objs)
  def is_visible(self, obj): return obj in self.seen
  def goto(self, recep): pass
  def open(self, recep): pass
  def close(self, recep): pass
"""


BOXES = [f"box {i}" for i in range(9)]


def room_demo(first: int) -> str:
    """An episode that sees, goes to and opens each box in turn (its state written after the call), then goes
    back to the first three, open by then."""
    boxes = BOXES[first:] + BOXES[:first]
    lines = ["env = Env()", "agent = Agent(env)"]
    for box in boxes:
        lines += [f"agent.look('{box}')", f"agent.goto('{box}')", f"env.set_property('{box}', 'open', False)",
                  f"agent.open('{box}')", f"env.set_property('{box}', 'open', True)"]
    return "\n".join([*lines, *(f"agent.goto('{box}')" for box in boxes[:3])]) + "\n"


def test_an_undemonstrated_close_is_not_given_the_visibility_open_and_goto_share() -> None:
    """`open` asks that the box be visible and closed, `goto` only that it be visible: `close`, never
    demonstrated, would otherwise assume visibility alone and be allowed on every visible box, closed or not."""
    with Sandbox(workers=2) as sandbox:
        inferred = Engine(sandbox, None).infer(InferRequest.model_validate({
            "spec": ROOM, "demonstrations": [room_demo(i) for i in range(3)],
            "options": {"generators": ["enumerate"], "library": "off",
                        "guarded": ["Agent.goto", "Agent.open", "Agent.close"]}}))
    assert "recep in self.seen" in inferred.preconditions["Agent.goto"]
    assert "not self.env.get_property(recep, 'open')" in inferred.preconditions["Agent.open"]
    assert inferred.preconditions["Agent.close"] == [UNSEEN_RULE]
    assert "not self.env.get_property(recep, 'open')" in inferred.warnings["Agent.close"]
