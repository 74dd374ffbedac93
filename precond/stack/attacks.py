"""One tenant attacks the shared service while another measures what it still gets (docs/security.md).

Shared by tests/service/test_shared_service.py (the attack bodies) and `python bench/reliability.py attacks`
(the figures: the victim's uncached check-actions and enumerate-only inference latencies and `/health`'s,
unloaded and under each attack, the gateway's resident size and whether any worker died).
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import queue
import time
from collections.abc import Awaitable, Callable
from multiprocessing.queues import Queue
from typing import Any

import httpx

from precond.stack import harness
from precond.stack.keyed import KeyedStack
from precond.stack.local import DEMOS, RULES, SPEC, check_body, infer_body
from precond_client.openai_log import Tool, spec_program

POISON_SPEC = ("class A:\n  def __init__(self):\n    self.x = 0\n  def act(self, a, b, c, d): pass\n"
               "  def q(self, " + ", ".join(f"p{i}" for i in range(14)) + "): return p0\n")
"""449 bytes: an action with 4 parameters and a pure query with 14 made the enumerator build 4^14 lists."""
POISON_BODY: dict[str, Any] = {"spec": POISON_SPEC, "demonstrations": ["a = A()\na.act(1, 2, 3, 4)\n"],
                               "options": {"generators": ["enumerate"]}}
SLEEPING_HISTORY = ("import typing\ntyping.sys.modules['time'].sleep(5)\n"  # waits, spends no CPU
                    "user = USER()\nsystem = SYSTEM(user)\n")


def deep_demonstration(terms: int = 1_500) -> str:
    """Parses (the parser's limit is far higher), but every recursive walk of its tree overflows the stack."""
    return "user = USER()\nsystem = SYSTEM(user)\nsystem.REQUEST(" + "+".join(["1"] * terms) + ")\n"


def unknown_fields_body(fields: int = 400_000) -> bytes:
    """An inference with `fields` unknown top-level fields first: one pydantic error object each, before."""
    filler = "".join(f'"{i:x}":0,' for i in range(fields))
    return ("{" + filler + httpx.Request("POST", "/", json=infer_body()).content.decode()[1:]).encode()


def unknown_act_body(methods: int = 850) -> dict[str, Any]:
    """A 200 KB check whose structured history has an unknown act: "did you mean" over 850 long names."""
    spec = "class USER:\n  def __init__(self): pass\n" + "".join(
        f"  def {'m' * 200}{i}(self): pass\n" for i in range(methods))
    return {"spec": spec, "history": [{"actor": "user", "act": "q" * 190}], "calls": ["user.SELECT()"]}


def oversized_set_body() -> dict[str, Any]:
    """3.8 MB of demonstrations, the last one broken: every one was parsed before the size bound applied."""
    return {"spec": SPEC, "preconditions": RULES, "demonstrations": [DEMOS[0] * 25] * 180 + ["system.REQUEST(("]}


def tool_call_check_body(seed: int = 0, tools: int = 258) -> dict[str, Any]:
    """A check of an agent's tool calls (`{"name", "arguments"}`) over a 62 KB spec of `tools` tools, in a body
    under the 64 KiB the gateway parses on its event loop: every such check made the gateway read the spec to
    render the calls, on the loop, before the cache lookup."""
    described = [Tool(f"lookup_{i}", ("reservation_id", "note"), frozenset({"reservation_id"}), "d" * 180)
                 for i in range(tools)]
    calls = [{"name": f"lookup_{i}", "arguments": {"reservation_id": f"R{seed}-{i}"}} for i in range(4)]
    return {"spec": spec_program(described, ()), "preconditions": {}, "calls": calls,
            "history": "user = USER()\nagent = AGENT(user)\n"}


def _sleeping_check(seed: int) -> dict[str, Any]:
    body = check_body(f"system.REQUEST('slow{seed}')")
    body["history"] = SLEEPING_HISTORY
    return body


Attack = Callable[[httpx.AsyncClient, int], Awaitable[Any]]
ATTACKS: dict[str, tuple[int, Attack]] = {
    # name: (concurrent attacker loops, one request of a loop)
    "1-crash": (2, lambda http, i: http.post("/infer-preconditions", content=unknown_fields_body(), headers={
        "Content-Type": "application/json"}) if i % 2 else http.post(
        "/infer-preconditions", json=infer_body(seed=i, demonstrations=[deep_demonstration()]))),
    "2-loop": (2, lambda http, i: http.post("/check-actions", json=unknown_act_body()) if i % 2 else http.post(
        "/precondition-sets", json=oversized_set_body())),
    "4-sets": (2, lambda http, i: http.post("/precondition-sets", json={
        "spec": SPEC, "preconditions": RULES, "demonstrations": [DEMOS[0] * 20 + f"# {i}\n", DEMOS[1] * 20]})),
    "5-sleep": (6, lambda http, i: http.post("/check-actions", json=_sleeping_check(i), params={"wait": 30})),
    "6-poison": (2, lambda http, i: http.post("/infer-preconditions", json={
        **POISON_BODY, "options": {"generators": ["enumerate"], "seed": i}}, params={"wait": 30})),
    "7-rate": (4, lambda http, i: http.get(f"/jobs/check-{i}") if i % 2 else http.get(
        "/jobs/x", headers={"Authorization": f"Bearer pk_guess{i}"})),
    "8-tool-calls": (24, lambda http, i: http.post("/check-actions", json=tool_call_check_body(i))),
}


async def _victim(base: str, key: str, stop: asyncio.Event) -> dict[str, list[float]]:
    """The other tenant: uncached checks and enumerate-only inferences one after the other, `/health` every
    50 ms; latencies in seconds."""
    seen: dict[str, list[float]] = {"check": [], "infer": [], "health": []}
    headers = {"Authorization": f"Bearer {key}"}
    serial = int(time.time() * 1000) % 2**30  # a fresh job per request (seeds are at most 2^31 - 1)

    async def loop(name: str, send: Callable[[httpx.AsyncClient, int], Awaitable[httpx.Response]],
                   pause: float) -> None:
        async with httpx.AsyncClient(base_url=base, headers=headers, timeout=60) as http:
            while not stop.is_set():
                started = time.perf_counter()
                answer = await send(http, serial + len(seen[name]))
                if answer.status_code == 200:
                    seen[name].append(time.perf_counter() - started)
                await asyncio.sleep(pause)

    await asyncio.gather(
        loop("check", lambda http, i: http.post("/check-actions", json=check_body(f"system.REQUEST('v{i}')")), 0),
        loop("infer", lambda http, i: http.post("/infer-preconditions", json=infer_body(seed=i)), 0),
        loop("health", lambda http, i: http.get("/health"), 0.05),
    )
    return seen


async def _attacker(base: str, key: str, attack: tuple[int, Attack], duration_s: float) -> dict[str, int]:
    loops, send = attack
    statuses: dict[str, int] = {}
    counter = iter(range(10**9))
    deadline = time.monotonic() + duration_s
    # From another loopback address: failed authentications are throttled per source, and the victim's is 127.0.0.1
    transport = httpx.AsyncHTTPTransport(local_address="127.0.0.2")
    async with httpx.AsyncClient(base_url=base, headers={"Authorization": f"Bearer {key}"}, timeout=60,
                                 transport=transport) as http:

        async def one_loop() -> None:
            while time.monotonic() < deadline:
                try:
                    status = str((await send(http, next(counter))).status_code)
                except httpx.HTTPError as exc:
                    status = type(exc).__name__
                statuses[status] = statuses.get(status, 0) + 1

        await asyncio.gather(*(one_loop() for _ in range(loops)))
    return statuses


def _attack_process(base: str, key: str, attack: str, duration_s: float, out: Queue[dict[str, int]]) -> None:
    out.put(asyncio.run(_attacker(base, key, ATTACKS[attack], duration_s)))


def phase(keyed: KeyedStack, attack: str | None, duration_s: float) -> dict[str, Any]:
    """The victim's figures for `duration_s` while `attack` runs (None: unloaded). The attacker runs in a process
    of its own: building its bodies must not stall the loop that measures the victim."""
    stack = keyed.stack
    gateway, workers = harness.gateway_pid(stack), stack.worker_pids()
    peak_rss = [0]
    context = multiprocessing.get_context("fork")
    out: Queue[dict[str, int]] = context.Queue()
    attacker = None if attack is None else context.Process(
        target=_attack_process, args=(stack.base_url, keyed.keys["attacker"], attack, duration_s, out))

    async def run() -> dict[str, list[float]]:
        stop = asyncio.Event()

        async def sample() -> None:
            while not stop.is_set():
                peak_rss[0] = max(peak_rss[0], harness.rss_kib(gateway))
                await asyncio.sleep(0.1)

        victim = asyncio.create_task(_victim(stack.base_url, keyed.keys["victim"], stop))
        sampler = asyncio.create_task(sample())
        await asyncio.sleep(duration_s)
        stop.set()
        await sampler
        return await victim

    if attacker is not None:
        attacker.start()
    seen = asyncio.run(run())
    statuses: dict[str, int] = {}
    if attacker is not None:
        with contextlib.suppress(queue.Empty):
            statuses = out.get(timeout=90)
        attacker.join(10)
        if attacker.is_alive():
            attacker.kill()
    return {
        "attack": attack or "none", "attacker_statuses": statuses,
        "check": harness.summary_ms(seen["check"]), "infer": harness.summary_ms(seen["infer"]),
        "health": harness.summary_ms(seen["health"]), "gateway_peak_mib": round(peak_rss[0] / 1024),
        "workers_died": sum(not harness.alive(pid) for pid in workers),
    }


def tenant_attacks(keyed: KeyedStack, duration_s: float, names: list[str] | None = None) -> list[dict[str, Any]]:
    """Unloaded, then each attack in turn (a pause between, for what an attack left queued to drain)."""
    figures = [phase(keyed, None, duration_s)]
    for name in names or list(ATTACKS):
        figures.append(phase(keyed, name, duration_s))
        time.sleep(6)
    return figures
