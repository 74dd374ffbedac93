"""The counterfactual metric end to end on a tiny domain through the real sandbox: which variants are made, which
points they are judged at, and that the truth scores 0 / 0 while 'always allowed' lets every refusal through."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from precond.evaluation import counterfactual
from precond.evaluation.cache import JsonCache
from precond.evaluation.domains import Domain
from precond.evaluation.scoring import Satisfaction
from precond.sandbox import Sandbox
from precond.sandbox.types import Point

SPEC = """\
class USER:
    def __init__(self):
        self.verified = False
        self.said_yes = False
    def VERIFY(self): self.verified = True
    def YES(self): self.said_yes = True

class SYSTEM:
    def __init__(self, user):
        self.user = user
        self.done = None
    def BLOCK(self): pass
    def result(self, ok): self.done = ok
    def NOTIFY(self): pass
"""
TESTS = (
    "user = USER()\nsystem = SYSTEM(user)\nuser.VERIFY()\nuser.YES()\nsystem.BLOCK()\nsystem.result(True)\n"
    "system.NOTIFY()\n",
    "user = USER()\nsystem = SYSTEM(user)\nuser.VERIFY()\nuser.YES()\nsystem.BLOCK()\nsystem.result(False)\n"
    "system.NOTIFY()\n",
)
ACTIONS = ("SYSTEM.BLOCK", "SYSTEM.NOTIFY")
GT = {"SYSTEM.BLOCK": ["self.user.verified", "self.user.said_yes"], "SYSTEM.NOTIFY": ["self.done is not None"]}


def _domain() -> Domain:
    points = {a: [Point(i, p, ()) for i, t in enumerate(TESTS) for p in range(2, len(t.splitlines()))]
              for a in ACTIONS}
    return Domain("tiny", "sgd", SPEC, (), ACTIONS, TESTS, ("d0", "d1"), points, GT)


@pytest.fixture(scope="module")
def sat(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Satisfaction]:
    with Sandbox() as sandbox:
        yield Satisfaction(sandbox, JsonCache(Path(tmp_path_factory.mktemp("cache"))))


def test_every_observation_may_be_removed_and_a_boolean_result_flipped() -> None:
    edits = counterfactual.possible_edits(TESTS[0], ACTIONS)
    assert [(e.position, e.change) for e in edits] == [
        (2, "removed"), (3, "removed"), (5, "removed"), (5, "flipped")]  # never an action, never a constructor
    flipped = counterfactual.apply(TESTS[0], edits[-1])
    assert "system.result(False)" in flipped and flipped.count("\n") == TESTS[0].count("\n")
    removed = counterfactual.apply(TESTS[0], edits[0])
    assert "user.VERIFY()" not in removed and removed.count("\n") == TESTS[0].count("\n") - 1


def test_variants_are_seeded_and_judged_only_after_their_change() -> None:
    domain = _domain()
    cf = counterfactual.counterfactual_domain(domain, variants=2, seed=7)
    again = counterfactual.counterfactual_domain(domain, variants=2, seed=7)
    assert cf.test == again.test and len(cf.test) == 4 and cf.name == "tiny~cf2s7"
    for variant, test_id in enumerate(cf.test_ids):
        change, position = test_id.split("~")[1].split("@")
        first = int(position) if change == "removed" else int(position) + 1
        judged = {p.position for p in cf.points["SYSTEM.BLOCK"] if p.demo == variant}
        assert judged and min(judged) >= first, (test_id, judged)


def test_the_truth_is_safe_and_no_rule_allows_every_refusal(sat: Satisfaction) -> None:
    cf = counterfactual.counterfactual_domain(_domain(), variants=4, seed=0)
    truth = counterfactual.score(cf, GT, sat)
    assert all(s.unsafe == 0 and s.over == 0 for s in truth.values())
    assert counterfactual.macro(truth) == {"unsafe_allow": 0.0, "over_refuse": 0.0}
    always = counterfactual.score(cf, {}, sat)
    assert counterfactual.macro(always)["unsafe_allow"] == 1.0
    # a correlate alone: BLOCK on "yes" only lets through the variants where the verification was removed
    partial = counterfactual.score(cf, {**GT, "SYSTEM.BLOCK": ["self.user.said_yes"]}, sat)["SYSTEM.BLOCK"]
    assert 0 < partial.unsafe < partial.refusals and partial.over == 0
