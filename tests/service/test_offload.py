"""Where the gateway does a request's CPU work: on the event loop when it is small, in the check pool's
processes when it is not. Rendering an agent's structured history costs its JSON characters divided by
`RENDER_SPEEDUP` (measured: 47 KB/ms rendered against 9.5 KB/ms parsed), so a 20 KB conversation no longer
pays the pool's round trip, and a large one still never holds the loop."""

from __future__ import annotations

import asyncio
import os

from precond.gateway.offload import INLINE_CHARS, CheckPool, rendering_chars

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
