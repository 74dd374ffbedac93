"""What the worker remembers of a request's text before the sandbox runs it (whether a program may be sent, what
names its spec defines, whether a rule is one expression) is remembered per tenant: the first request of a text
that another tenant sent before reads it afresh. Remembered by the text alone, it would answer that request
measurably sooner (seconds for a 100 KB spec) and tell its sender that someone else sent the same text (the
timing attack docs/security.md describes for the model's prompt cache)."""

from __future__ import annotations

import ast
import uuid
from typing import Any

import pytest

from precond.engine.engine import Engine
from precond.engine.scope import scoped
from precond.sandbox import Sandbox, astfilter, plain
from precond_client.schemas import CheckRequest, InferRequest


class CountingAst:
    """The `ast` module as the worker's text checks see it, counting each text they parse."""

    def __init__(self) -> None:
        self.parsed: list[str] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(ast, name)

    def parse(self, source: str, *args: Any, **kwargs: Any) -> ast.AST:
        self.parsed.append(source)
        return ast.parse(source, *args, **kwargs)


@pytest.fixture()
def counting(monkeypatch: pytest.MonkeyPatch) -> CountingAst:
    counting = CountingAst()
    monkeypatch.setattr(astfilter, "ast", counting)
    monkeypatch.setattr(plain, "ast", counting)
    return counting


def test_a_spec_another_tenant_checked_is_read_afresh(small: Sandbox, counting: CountingAst) -> None:
    spec = f"# {uuid.uuid4().hex}\nclass Door:\n    def lock(self):\n        self.locked = True\n" \
           "    def open(self):\n        pass\n"
    rule = f"not self.locked or '{uuid.uuid4().hex}' == ''"

    def reads(scope: str) -> tuple[int, int]:
        """How often the spec and the rule were parsed for one check of `scope`."""
        counting.parsed.clear()
        (verdict,) = small.check(spec, {"Door.open": [rule]}, "door = Door()\ndoor.lock()\n", ["door.open()"], scope)
        assert not verdict.allowed and verdict.violations == (rule,)
        return counting.parsed.count(spec), counting.parsed.count(rule)

    first = reads("tenant-a")
    assert first[0] >= 1 and first[1] >= 1
    assert reads("tenant-a") == (0, 0)  # remembered for the tenant that sent it
    assert reads("tenant-b") == first  # never served from tenant-a's memory


def test_an_inferences_programs_are_read_afresh_for_another_tenant(small: Sandbox, counting: CountingAst) -> None:
    spec = f"# {uuid.uuid4().hex}\nclass A:\n    def act(self, v):\n        pass\n"
    demonstration = f"a = A()\na.act({uuid.uuid4().int % 1000})\n"

    def reads(scope: str) -> tuple[int, int]:
        counting.parsed.clear()
        small.trace(spec, [demonstration], scope=scope)
        small.evaluate(spec, [demonstration], {"A.act": ["v > 0"]}, scope=scope)
        return counting.parsed.count(spec), counting.parsed.count(demonstration)

    first = reads("tenant-a")
    assert first[0] >= 1 and first[1] >= 1
    assert reads("tenant-a") == (0, 0)
    assert reads("tenant-b") == first


def test_the_engine_reads_a_jobs_text_in_its_tenants_scope(small: Sandbox, counting: CountingAst) -> None:
    """The worker runs a job in its tenant's scope (`engine.scope`); the engine's inference and check pass it on."""
    spec = f"# {uuid.uuid4().hex}\nclass A:\n    def __init__(self):\n        self.on = False\n" \
           "    def start(self):\n        self.on = True\n    def act(self, v):\n        pass\n"
    engine = Engine(small, None)
    infer = InferRequest(spec=spec, demonstrations=["a = A()\na.start()\na.act(1)\n"],
                         options={"generators": ["enumerate"]})
    check = CheckRequest(spec=spec, preconditions={"A.act": ["self.on"]}, history="a = A()\n", calls=["a.act(1)"])

    def reads(scope: str) -> int:
        counting.parsed.clear()
        with scoped(scope):
            engine.infer(infer)
            engine.check(check)
        return counting.parsed.count(spec)

    first = reads("tenant-a")
    assert first >= 1
    assert reads("tenant-a") == 0
    assert reads("tenant-b") == first
