"""A job runs in its tenant's cache scope, so the model reuses only that tenant's prompt prefixes."""

from __future__ import annotations

from functools import partial
from typing import Any

from precond.engine.scope import current
from precond.jobs.queue.keys import JobId, job_id, tenant_tag
from precond.worker.jobs import _outcome
from precond.worker.memory import MemoryGuard
from precond_client.schemas import CheckRequest, CheckResponse


class SeesScope:
    def __init__(self) -> None:
        self.seen: list[str] = []

    def check(self, request: CheckRequest, screened: bool = False) -> CheckResponse:
        self.seen.append(current())
        return CheckResponse(results=[])


def test_the_engine_runs_in_the_jobs_tenant_scope_and_leaves_it_after() -> None:
    engine = SeesScope()
    body: dict[str, Any] = {"spec": "class A:\n    def go(self):\n        pass\n", "history": "a = A()\n",
                            "calls": ["a.go()"]}
    secret = b"s" * 32
    ident = job_id("check", body, None, secret, tenant_tag(secret, "tenant-a"))
    outcome, _ = _outcome(lambda: engine, "check", body, lambda *a: None, lambda: False,  # type: ignore[arg-type,return-value]
                          10**6, JobId.parse(ident).tenant, partial(MemoryGuard(2**30).running, ident))
    assert outcome.status == "succeeded", outcome
    assert engine.seen == [tenant_tag(secret, "tenant-a")] and current() == ""
