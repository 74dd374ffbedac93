"""Where the gateway does a request's CPU work: on the event loop when it is small, in the check pool's
processes when it is not. Rendering an agent's structured history costs its JSON characters divided by
`RENDER_SPEEDUP` (measured: 47 KB/ms rendered against 9.5 KB/ms parsed), so a 20 KB conversation no longer
pays the pool's round trip, and a large one still never holds the loop."""

from __future__ import annotations

import asyncio
import os
import uuid
from types import SimpleNamespace

import pytest

from precond.gateway import offload
from precond.gateway.offload import INLINE_CHARS, CheckPool, rendering_chars
from precond.gateway.routes.operations import screened_check
from precond.programs import checks
from precond.stack.attacks import tool_call_check_body
from precond_client.schemas import CheckRequest

SPEC = "class AGENT:\n    def cancel_reservation(self, reservation_id): pass\n" * 40


def where_it_runs(chars: int) -> int:
    pool = CheckPool(1, 1)
    try:
        return asyncio.run(pool.run("tenant-tag", chars, os.getpid))
    finally:
        pool.close()


def test_an_agents_conversation_is_rendered_on_the_loop() -> None:
    assert where_it_runs(rendering_chars(SPEC, 20_000)) == os.getpid()


def test_a_large_history_is_rendered_in_the_pool() -> None:
    chars = rendering_chars(SPEC, 400_000)
    assert chars > INLINE_CHARS
    assert where_it_runs(chars) != os.getpid()


def test_a_tool_call_checks_spec_is_read_off_the_loop_or_once_per_tenant(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rendering `{"name", "arguments"}` calls reads the spec's tools: a 62 KB spec is read in the pool, never on
    the loop, however many checks send it; a small one on the loop once per tenant (then remembered)."""
    parsed: list[int] = []
    real = checks.spec_methods
    monkeypatch.setattr(checks, "spec_methods", lambda source: parsed.append(len(source)) or real(source))
    large = CheckRequest.model_validate(tool_call_check_body())
    small = CheckRequest.model_validate(tool_call_check_body(tools=4))
    pool = CheckPool(1, 1)

    async def render(tag: str, body: CheckRequest) -> list[str]:
        services = SimpleNamespace(checks=pool, settings=SimpleNamespace(interpret_checks=True))
        outcome = await screened_check(services, tag, body)  # type: ignore[arg-type]
        assert isinstance(outcome, offload.Queued), outcome
        return outcome.lines

    async def scenario() -> None:
        for _ in range(3):
            assert await render("tenant-a", large) == ["agent.lookup_0('R0-0', None)", "agent.lookup_1('R0-1', None)",
                                                       "agent.lookup_2('R0-2', None)", "agent.lookup_3('R0-3', None)"]
        assert parsed == []
        a, b = f"tenant-a-{uuid.uuid4().hex}", f"tenant-b-{uuid.uuid4().hex}"  # new to this process's memory
        for tag in (a, a, a, b, b):
            await render(tag, small)
        assert parsed == [len(small.spec_text())] * 2

    try:
        asyncio.run(scenario())
    finally:
        pool.close()


def test_a_rule_that_walks_a_collection_is_judged_in_the_pool() -> None:
    walking = ["sum(self.results['get_order_details'][order_id]['prices']) <= 10",
               "max(self.results['get_order_details'][order_id]['prices']) <= 10",
               "all(x for x in self.results['get_order_details'][order_id]['prices'])"]
    assert all(offload.iterating_rules({"AGENT.pay": [rule]}) for rule in walking)
    assert not offload.iterating_rules({"AGENT.pay": ["order_id in self.results['get_order_details']"]})
