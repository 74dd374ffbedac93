"""A never-demonstrated guarded action assumes the conditions the other guarded actions share
(precond/engine/judging/unseen_shared.py) instead of `options.unseen`'s placeholder, only where they are shared,
name its parameters and agree with its labelled calls."""

from __future__ import annotations

from precond.engine.judging.counterexamples import Outcome, Separation
from precond.engine.judging.ranking import Candidate
from precond.engine.judging.report import UNSEEN_RULE, Ranked
from precond.engine.judging.unseen_shared import assume_shared
from precond.engine.spec import parse_spec

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
