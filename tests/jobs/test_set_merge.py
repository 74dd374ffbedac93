"""The merge of a re-inference with its base version, as a pure function (precond/store/reinference.py): required
rules kept, rejected ones kept out, and every base rule accounted for in the diff with a reason when it is gone; and the
store of the version it makes (precond/store/reinference.py), on a stand-in for Redis."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import pytest

from precond.jobs.queue.payloads import ReinferJob
from precond.store.reinference import explain_removed, merge, store
from precond.store.sets import normal, union
from precond.store.tenant_store import CONFLICT
from precond.worker.reinfer import reinfer
from precond_client.schemas import CandidateReport, PreconditionSet, ValidateResponse
from precond_client.schemas.errors import Conflict, InvalidInput


def _base(**changes: object) -> PreconditionSet:
    fields: dict[str, object] = {
        "id": "ps_" + "a" * 24, "version": 3, "latest": 3, "reference": "ps_" + "a" * 24 + "@3", "created": "now",
        "spec": "class A:\n  def act(self): pass\n",
        "preconditions": {"A.act": ["self.x", "self.y", "self.z"], "A.other": ["self.w"]},
        "required": {"A.act": ["self.y"]}, "rejected": {"A.act": ["self.bad"]},
    }
    return PreconditionSet.model_validate(fields | changes)


def _candidate(assertion: str, kept: bool, reason: str) -> CandidateReport:
    return CandidateReport(assertion=assertion, source="enumerate", valid=kept, support=1, kept=kept, reason=reason)


def test_required_rules_stay_rejected_never_return_and_the_diff_accounts_for_every_rule() -> None:
    inferred = {"A.act": ["self.x", "self.bad", "self.new"], "A.other": []}
    candidates = {"A.act": [_candidate("self.x", True, "kept: argument condition"),
                            _candidate("self.bad", True, "kept"),
                            _candidate("self.new", True, "kept: made true since the agent's previous turn"),
                            _candidate("self.z", False, "violated at demonstration 4, line 7, system.act()")]}
    merged = merge(_base(), inferred, candidates, new_demonstrations=2)
    assert merged.preconditions == {"A.act": ["self.y", "self.x", "self.new"]}
    diff = merged.diff
    assert diff.base_version == 3 and diff.new_demonstrations == 2
    assert [(c.rule, c.reason) for c in diff.required_kept] == [("self.y", "marked required")]
    assert [c.rule for c in diff.kept] == ["self.x"] and diff.kept[0].reason == "kept: argument condition"
    assert [c.rule for c in diff.added] == ["self.new"]
    assert [c.rule for c in diff.rejected_suppressed] == ["self.bad"]
    assert [(c.rule, c.reason) for c in diff.removed] == [
        ("self.z", "violated at demonstration 4, line 7, system.act()")]
    # self.w was neither proposed nor judged: the caller judges it against the demonstrations
    assert merged.unexplained == {"A.other": ["self.w"]}
    explained = explain_removed(merged, {("A.other", "self.w"): "demonstrations[0], line 3 (a.other())"})
    assert explained.removed[-1].rule == "self.w"
    assert explained.removed[-1].reason == "violated at demonstrations[0], line 3 (a.other())"
    still = explain_removed(merged, {})
    assert "still holds at every demonstration" in (still.removed[-1].reason or "")


def test_rules_compare_by_their_canonical_text() -> None:
    assert normal("self.a  and (self.b)") == normal("self.a and self.b")
    base = _base(preconditions={"A.act": ["self.a and self.b"]}, required={}, rejected={"A.act": ["not  self.c"]})
    merged = merge(base, {"A.act": ["self.a  and  self.b", "(not self.c)"]}, {})
    assert merged.preconditions == {"A.act": ["self.a  and  self.b"]}
    assert [c.rule for c in merged.diff.kept] == ["self.a  and  self.b"] and not merged.diff.removed
    assert [c.rule for c in merged.diff.rejected_suppressed] == ["(not self.c)"]


def test_a_required_rule_the_inference_also_finds_is_listed_once() -> None:
    merged = merge(_base(), {"A.act": ["self.y"]}, {})
    assert merged.preconditions["A.act"] == ["self.y"]
    assert [c.rule for c in merged.diff.required_kept] == ["self.y"] and not merged.diff.kept


def test_the_union_keeps_stored_demonstrations_first_and_each_once() -> None:
    assert union(["a", "b"], ["b", "c", "c"]) == ["a", "b", "c"]


def test_actions_not_re_inferred_keep_their_rules() -> None:
    merged = merge(_base(), {"A.act": ["self.x"]}, {}, actions=["A.act"])
    assert merged.preconditions == {"A.act": ["self.y", "self.x"], "A.other": ["self.w"]}
    assert ("A.other", "self.w", "not re-inferred (not in `actions`)") in {
        (c.action, c.rule, c.reason) for c in merged.diff.kept}
    assert merged.unexplained == {"A.act": ["self.z"]}  # re-inferred and gone: to be explained



class _Stored:
    """A set whose version 4 is stored already: `evalsha` (the store's script) answers conflict, `hget` reads."""

    def __init__(self, version: PreconditionSet) -> None:
        self.hash = {b"latest": b"4", b"4": version.model_dump_json().encode()}

    async def evalsha(self, *args: object) -> int:
        return CONFLICT

    async def hget(self, key: str, field: str) -> bytes | None:
        return self.hash.get(field.encode())


def test_a_re_run_of_a_reinference_that_stored_its_version_answers_that_version() -> None:
    """A worker that died after storing: the job, handed back and run again, finds its own version there."""
    base = _base()
    job = ReinferJob(base=base, demonstrations=["x = 1"], max_versions=10, max_bytes=10**6)
    mine = base.model_copy(update={"version": 4, "latest": 4, "reference": f"{base.id}@4", "created": "then"})
    again = mine.model_copy(update={"created": "now"})
    assert asyncio.run(store(_Stored(mine), "tag", job, again)).created == "then"
    other = mine.model_copy(update={"preconditions": {"A.act": ["self.q"]}})
    with pytest.raises(Conflict):
        asyncio.run(store(_Stored(other), "tag", job, again))


class InfersMore:
    """An engine whose inference keeps 8 rules of `A.act` besides the base version's: the version would hold 40."""

    def validate(self, spec: str, rules: object, demonstrations: object) -> ValidateResponse:
        return ValidateResponse()

    def infer(self, request: object, progress: object, cancelled: object) -> SimpleNamespace:
        return SimpleNamespace(preconditions={"A.act": [f"self.n{i}" for i in range(8)]}, candidates={},
                               evidence={}, warnings={})


def test_a_reinferred_version_over_an_actions_rule_bound_is_refused_never_stored() -> None:
    required = [f"self.r{i}" for i in range(32)]
    base = _base(preconditions={"A.act": required}, required={"A.act": required}, rejected={})
    job = ReinferJob(base=base, demonstrations=["a = A()\na.act()\n"], max_versions=50, max_bytes=10**6,
                     max_tenant_bytes=10**7)
    with pytest.raises(InvalidInput, match=r"A\.act would have 40 rules, over the 32 one action may have"):
        reinfer(InfersMore(), job, lambda *a: None, lambda: False)  # type: ignore[arg-type]
