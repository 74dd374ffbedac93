"""C_a computed end to end through the real sandbox on a tiny domain: GT scores 1.0, edge cases hold."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import pytest

from precond.evaluation.cache import JsonCache
from precond.evaluation.domains import Domain
from precond.evaluation.metrics import PRF, domain_macro
from precond.evaluation.scoring import Satisfaction, conjunction, score
from precond.sandbox import Sandbox
from precond.sandbox.types import EvaluateResult, Point

SPEC = """\
class Door:
    def __init__(self):
        self.open = False
        self.keys = {}
    def unlock(self, key):
        self.keys[key] = True
    def toggle(self):
        self.open = not self.open
    def enter(self):
        pass
    def use(self, key):
        pass
"""
TESTS = (
    "door = Door()\ndoor.toggle()\ndoor.enter()\ndoor.toggle()\n",
    "door = Door()\ndoor.unlock('red')\ndoor.use('red')\n",
)


def _domain() -> Domain:
    enter = [Point(i, p, ()) for i, t in enumerate(TESTS) for p in range(len(t.splitlines()))]
    use = [Point(i, p, (k,)) for i, t in enumerate(TESTS)
           for p in range(len(t.splitlines())) for k in ("red", "blue")]
    return Domain("toy", "sgd", SPEC, (TESTS[0],), ("Door.enter", "Door.use"), TESTS, ("a", "b"),
                  {"Door.enter": enter, "Door.use": use},
                  {"Door.enter": ["self.open"], "Door.use": ["self.keys[key]"]})


@pytest.fixture(scope="module")
def sandbox() -> Iterator[Sandbox]:
    with Sandbox() as box:
        yield box


def test_ground_truth_scores_one(sandbox: Sandbox, tmp_path: Path) -> None:
    domain = _domain()
    scores = score(domain, domain.gt, Satisfaction(sandbox, JsonCache(tmp_path)))
    assert domain_macro(scores) == PRF(1.0, 1.0, 1.0)
    assert scores["Door.enter"].n_gt == 2  # before `door.enter()` and before the second toggle


def test_always_allowed_has_full_recall(sandbox: Sandbox, tmp_path: Path) -> None:
    domain = _domain()
    scores = score(domain, {}, Satisfaction(sandbox, JsonCache(tmp_path)))
    enter = scores["Door.enter"]
    # position 0 (before `door = Door()`) has no instance yet: not satisfied even by `True`
    assert (enter.n_pred, enter.n_gt, enter.prf) == (5, 2, PRF(0.4, 1.0, pytest.approx(4 / 7)))


def test_an_assertion_that_raises_is_not_satisfied(sandbox: Sandbox, tmp_path: Path) -> None:
    domain = _domain()
    sat = Satisfaction(sandbox, JsonCache(tmp_path))
    # `self.keys[key]` raises KeyError wherever the key was never unlocked: those points are "not satisfied"
    sets = sat.bitsets(domain, {"Door.use": ["self.keys[key]", "1 / 0 == 1"]})["Door.use"]
    red_after_unlock = [k for k, p in enumerate(domain.points["Door.use"]) if p == Point(1, 2, ("red",))]
    assert sets["self.keys[key]"] == 1 << red_after_unlock[0]
    assert sets["1 / 0 == 1"] == 0


def test_prediction_is_a_conjunction_and_empty_means_true() -> None:
    assert conjunction([]) == "True"
    assert conjunction(["a"]) == "a"
    assert conjunction(["a or b", "c"]) == "(a or b) and (c)"


class CountingEvaluator:
    def __init__(self, inner: Sandbox) -> None:
        self.inner, self.calls = inner, 0

    def evaluate(self, spec: str, demonstrations: Sequence[str], candidates: Mapping[str, Sequence[str]],
                 points: Mapping[str, Sequence[Point]] | None = None) -> EvaluateResult:
        self.calls += 1
        return self.inner.evaluate(spec, demonstrations, candidates, points)


def test_chunks_agree_with_one_call_and_the_cache_is_reused(sandbox: Sandbox, tmp_path: Path) -> None:
    domain = _domain()
    asked = {"Door.enter": ["not self.open"]}
    whole = Satisfaction(sandbox, JsonCache(tmp_path / "a")).bitsets(domain, asked)
    counting = CountingEvaluator(sandbox)
    chunked = Satisfaction(counting, JsonCache(tmp_path / "b"), chunk=1)
    assert chunked.bitsets(domain, {"Door.enter": ["not self.open"]}) == whole
    assert counting.calls == 2
    assert chunked.bitsets(domain, {"Door.enter": ["not self.open"]}) == whole
    assert counting.calls == 2
