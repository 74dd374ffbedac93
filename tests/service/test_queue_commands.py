"""What one check costs the queue Redis on the queue path, counted by the real redis-server (MONITOR): every
command a client sends, and every command the queue's scripts run inside Redis. The count is what the
contract's steps do per job (submit, take, finish, the result cache's read and write), so a step that grows a
command, or a write that leaves a script for a round trip of its own, shows here."""

from __future__ import annotations

import re
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from precond.stack.local import Stack, check_body, make_stack, serving

pytestmark = pytest.mark.stack

MAX_ROUND_TRIPS = 5
"""The result cache's read (a miss), the submit, the take, the result cache's write and the finish."""
MAX_COMMANDS = 38
"""Those five and the commands their scripts run: the bound, the tenant's cap, the fair place, the job and its
waiter, the wake-up; the in-progress mark, the job's bytes, its try and its claim; the end, its keys' removal,
the claim's release, the notice and the queue's depth."""
STOP = "queue-commands:stop"


@pytest.fixture(scope="module")
def quiet_stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[Stack]:
    """A worker on the check queue alone, beating rarely: few commands beside the checks' own."""
    stack = make_stack(tmp_path_factory.mktemp("stack"), tiny_model_dir, PRECOND_WORKER_QUEUES="precond:queue:check",
                       PRECOND_HEARTBEAT_S="30")
    with serving(stack, workers=1):
        yield stack


def monitored(stack: Stack, run: Any) -> list[dict[str, Any]]:
    """The commands Redis ran while `run()` ran, in order (each script's own commands right after its call)."""
    seen: list[dict[str, Any]] = []
    started = threading.Event()

    def listen() -> None:
        with stack.redis.client().monitor() as monitor:
            started.set()
            for command in monitor.listen():
                if STOP in command["command"]:
                    return
                seen.append(command)

    thread = threading.Thread(target=listen)
    thread.start()
    started.wait(10)
    try:
        run()
    finally:
        stack.redis.client().get(STOP)
        thread.join(30)
    return seen


def of_job(commands: list[dict[str, Any]], marker: str) -> list[list[str]]:
    """The client commands that touch the job whose record holds `marker` (its id or its cache key named), each
    with the commands its script ran."""
    groups: list[list[str]] = []
    for command in commands:
        if command.get("client_type") == "lua" and groups:
            groups[-1].append(command["command"])
        else:
            groups.append([command["command"]])
    record = next(line for group in groups for line in group if marker in line and "arq:job:" in line)
    job = re.search(r"arq:job:(\S+)", record)
    cache = re.search(r'"cache_key\\*":\s*\\*"([^"\\]+)', record)
    assert job is not None and cache is not None, record
    names = (job.group(1), cache.group(1))
    return [group for group in groups if any(name in line for line in group for name in names)]


def test_one_queued_check_costs_redis_a_bounded_number_of_commands(quiet_stack: Stack) -> None:
    with quiet_stack.http(timeout=60) as client:
        def check(n: int) -> None:
            answer = client.post("/check-actions", json=check_body(f"system.REQUEST('commands_{n}')"),
                                 params={"wait": 30})
            assert answer.status_code == 200, answer.text
            assert answer.json()["judged_by"] != "interpreter"

        check(0)  # the scripts loaded, the tenant's rate lease taken
        commands = monitored(quiet_stack, lambda: check(1))
    groups = of_job(commands, "commands_1")
    listing = "\n".join(" | ".join(line[:100] for line in group) for group in groups)
    assert len(groups) <= MAX_ROUND_TRIPS, listing
    assert sum(map(len, groups)) <= MAX_COMMANDS, listing
