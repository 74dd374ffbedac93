"""The client's helpers for precondition sets and structured histories against a real keyed stack, sync and
async alike: create, read, edit (typed rule edits), re-infer (a job followed to its version and diff), check
with a set reference and a `History`; typed errors (`NotFound`, `Conflict`, `InvalidInput` with its field)."""

from __future__ import annotations

import asyncio

import pytest

from precond.stack.keyed import KeyedStack
from precond.stack.local import DEMOS, SPEC
from precond_client import (
    AsyncClient,
    Client,
    Conflict,
    History,
    HistoryEvent,
    InferOptions,
    InvalidInput,
    JobStatus,
    NotFound,
    PreconditionSet,
    event,
    rules,
)

ENUMERATE = InferOptions(generators=["enumerate"], library=False)  # the demonstrations alone: two dialogs, assumed
HISTORY = History().user("INFORM_INTENT", "FindRestaurants").system("REQUEST", "city").user("INFORM", "city")


def test_history_builds_typed_events_and_refuses_what_is_not_a_scalar() -> None:
    assert HISTORY.events[0] == HistoryEvent(actor="user", act="INFORM_INTENT", args=["FindRestaurants"])
    assert event("system", "GOODBYE") == HistoryEvent(actor="system", act="GOODBYE", args=[])
    assert len(HISTORY.copy().user("REQUEST", "phone_number")) == len(HISTORY) + 1
    with pytest.raises(TypeError, match="argument 0 is a list"):
        event("user", "INFORM", ["city"])  # type: ignore[arg-type]
    assert rules.reject("SYSTEM.INFORM", "x").op == "reject"


def test_sets_round_trip_with_the_blocking_client(keyed: KeyedStack) -> None:
    seen: list[JobStatus] = []
    with Client(keyed.url, api_key=keyed.keys["acme"]) as client:
        made = client.create_set({"spec": SPEC, "demonstrations": [DEMOS[0]],
                                  "preconditions": {"SYSTEM.INFORM": ["self.user.requested_slot[slot]"]}})
        assert isinstance(made, PreconditionSet) and made.reference == f"{made.id}@1"
        assert client.get_set(made.reference) == made
        pinned = client.edit_set(made.id, [rules.require("SYSTEM.INFORM", "self.user.requested_slot[slot]")],
                                 base_version=1)
        assert pinned.version == 2 and pinned.required == {"SYSTEM.INFORM": ["self.user.requested_slot[slot]"]}
        with pytest.raises(Conflict) as stale:
            client.edit_set(made.id, [rules.remove("SYSTEM.INFORM", "self.user.requested_slot[slot]")],
                            base_version=1)
        assert stale.value.status == 409
        redone = client.reinfer_set(made.id, [DEMOS[1]], options=ENUMERATE, base_version=2, wait=0,
                                    progress=seen.append)
        assert redone.version == 3 and redone.diff is not None and redone.diff.base_version == 2
        assert [c.rule for c in redone.diff.required_kept] == ["self.user.requested_slot[slot]"]
        assert redone.demonstrations == DEMOS and seen and seen[-1].status == "succeeded"
        verdicts = client.check_with_set(redone.reference, HISTORY.copy().user("REQUEST", "phone_number"),
                                         ["system.INFORM('phone_number')", "system.INFORM('cuisine')"])
        assert [v.allowed for v in verdicts.results] == [True, False]
        # next-action with the set and events: a typed answer from the (tiny) model, verified against the set
        predicted = client.next_action_with_set(
            redone.reference, HISTORY, demonstrations=[DEMOS[0]],
            options={"max_attempts": 1, "max_new_tokens": 8}, timeout=120,
        )
        assert len(predicted.actions) == 1 and predicted.actions[0].attempts >= 1
        with pytest.raises(InvalidInput) as bad:
            client.reinfer_set(made.id, [DEMOS[1], "user = USER(\n"], options=ENUMERATE)
        assert bad.value.field == "demonstrations[1]"
        with pytest.raises(NotFound):
            client.get_set("ps_" + "0" * 24)
        listed = client.list_sets(limit=100)
        mine = next(s for s in listed.sets if s.id == made.id)
        assert mine.latest == 3 and mine.rules == sum(map(len, redone.preconditions.values()))
        assert mine.no_evidence == 0 and mine.assumed > 0  # re-inferred: evidence; two dialogs: rules assumed
    with Client(keyed.url, api_key=keyed.keys["cli"]) as other, pytest.raises(NotFound):
        other.reinfer_set(made.id, [DEMOS[1]], options=ENUMERATE)  # another tenant's set: not found


def test_the_async_client_has_the_same_helpers(keyed: KeyedStack) -> None:
    async def run() -> tuple[PreconditionSet, PreconditionSet, list[bool]]:
        async with AsyncClient(keyed.url, api_key=keyed.keys["acme"]) as client:
            made = await client.create_set({"spec": SPEC, "demonstrations": [DEMOS[0]],
                                            "preconditions": {"SYSTEM.GOODBYE": ["self.user.no_more"]}})
            edited = await client.edit_set(made.id, [rules.add("SYSTEM.INFORM", "self.user.requested_slot[slot]")])
            redone = await client.reinfer_set(made.id, [DEMOS[1]], actions=["SYSTEM.INFORM"], options=ENUMERATE)
            verdicts = await client.check_with_set(redone.id, HISTORY, ["system.GOODBYE()"])
            assert (await client.get_set(f"{made.id}@2")).preconditions == edited.preconditions
            assert made.id in {s.id for s in (await client.list_sets(limit=100)).sets}
            return edited, redone, [v.allowed for v in verdicts.results]

    edited, redone, allowed = asyncio.run(run())
    assert edited.version == 2 and redone.version == 3 and allowed == [False]
    assert redone.diff is not None and redone.preconditions["SYSTEM.GOODBYE"] == ["self.user.no_more"]
    assert ("SYSTEM.GOODBYE", "self.user.no_more") in {(c.action, c.rule) for c in redone.diff.kept}
