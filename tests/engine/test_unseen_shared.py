"""A never-demonstrated guarded action assumes the conditions the other guarded actions share
(precond/engine/judging/unseen_shared.py) instead of `options.unseen`'s placeholder, only where they are shared,
name its parameters and agree with its labelled calls."""

from __future__ import annotations

from precond.convert.openai import convert
from precond.engine.engine import Engine
from precond.engine.judging.counterexamples import Outcome, Separation
from precond.engine.judging.ranking import Candidate
from precond.engine.judging.report import UNSEEN_RULE, Ranked
from precond.engine.judging.unseen_shared import assume_shared
from precond.engine.spec import parse_spec
from precond.sandbox import Sandbox
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
    assume_shared(chosen, rankings, separated or {}, list(chosen), SPEC.methods)
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
