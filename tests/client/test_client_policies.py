"""The client's helpers for trained policies against a real keyed stack (the tiny model stands in for the
real one): train (a job followed to the stored policy), list, read, retrain, name it in a next action, delete;
typed errors (`NotFound` for another tenant's policy, `InvalidInput` naming the field)."""

from __future__ import annotations

import asyncio

import pytest

from precond.stack.keyed import KeyedStack
from precond.stack.local import DEMOS, SPEC, example
from precond_client import (
    AsyncClient,
    Client,
    InvalidInput,
    JobStatus,
    NotFound,
    PolicyAdapter,
    TrainPolicyOptions,
    TrainPolicyRequest,
)

REQUEST = TrainPolicyRequest(spec=SPEC, demonstrations=DEMOS[:2], options=TrainPolicyOptions(steps=2, max_tokens=1024))


def test_a_policy_round_trip_with_the_blocking_client(keyed: KeyedStack) -> None:
    seen: list[JobStatus] = []
    with Client(keyed.url, api_key=keyed.keys["acme"]) as client, \
            Client(keyed.url, api_key=keyed.keys["light"]) as other:
        policy = client.train_policy(REQUEST, wait=0, progress=seen.append, timeout=120)
        assert isinstance(policy, PolicyAdapter) and policy.reference == f"{policy.id}@1"
        assert seen and seen[-1].status == "succeeded" and policy.result.steps == 2
        try:
            assert client.get_policy(policy.id) == policy
            assert [p.id for p in client.list_policies().adapters] == [policy.id]
            again = client.train_policy(REQUEST, adapter=policy.id, timeout=120)
            assert (again.id, again.version) == (policy.id, 2)
            asked = example("next-action") | {"options": {"policy": f"adapter:{policy.reference}"}}
            answer = client.next_action(asked, timeout=120)
            assert answer.model is not None and (answer.model.adapter or "").startswith(f"{policy.id}-v1@")
            with pytest.raises(NotFound):
                other.get_policy(policy.id)
            with pytest.raises(NotFound):
                other.next_action(asked, timeout=120)
            with pytest.raises(InvalidInput) as bad:
                client.get_policy("../precondition-sets")
            assert bad.value.field == "adapter"
        finally:
            client.delete_policy(policy.id)
        with pytest.raises(NotFound):
            client.get_policy(policy.id)


def test_the_async_client_trains_and_deletes_alike(keyed: KeyedStack) -> None:
    async def run() -> None:
        async with AsyncClient(keyed.url, api_key=keyed.keys["light"]) as client:
            policy = await client.train_policy(REQUEST.model_dump(), timeout=120)
            assert (await client.list_policies()).adapters == [policy]
            await client.delete_policy(policy.id)
            assert (await client.list_policies()).adapters == []

    asyncio.run(run())
