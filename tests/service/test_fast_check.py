"""The check route's short way in (`precond.gateway.fast_check`) on a real stack with API keys: every answer is the
one FastAPI's handler gives (the same body sent with a query the short way leaves to FastAPI), a cached check
found by its body's digest is answered as the first time, per tenant, and a request handed on to FastAPI's
handler neither takes a second token nor counts a second failed authentication."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from precond.gateway.fast_check import CheckMemo, Known, plain_wait
from precond.stack.local import Stack, check_body, make_stack, serving
from tests.service.test_interpreted_http import sandboxed
from tests.service.test_tenants import client_for, make_key

BURST = 40


@pytest.fixture(scope="module")
def keys_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("keys") / "keys.jsonl"


@pytest.fixture(scope="module")
def keys(keys_file: Path) -> dict[str, str]:
    return {tenant: make_key(keys_file, tenant)[1] for tenant in ("acme", "globex", "limited")}


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path, keys_file: Path,
          keys: dict[str, str]) -> Iterator[Stack]:
    stack = make_stack(tmp_path_factory.mktemp("fast-check"), tiny_model_dir, PRECOND_API_KEYS_FILE=str(keys_file),
                       PRECOND_INTERPRET_CHECKS="true", PRECOND_TENANT_RATE_PER_S="0.01",
                       PRECOND_TENANT_BURST=str(BURST), PRECOND_AUTH_FAILURES_PER_S="0.01",
                       PRECOND_AUTH_FAILURE_BURST="3")
    with serving(stack, workers=1):
        yield stack


def _same(short: httpx.Response, long: httpx.Response) -> None:
    assert short.status_code == long.status_code, (short.text, long.text)
    assert short.headers["content-type"] == long.headers["content-type"]
    assert short.headers.get("X-Job-Id") == long.headers.get("X-Job-Id")
    if short.status_code == 200:
        assert short.content == long.content
    else:  # the request id differs: the error itself must not
        assert short.json()["error"] == long.json()["error"]


BODIES: dict[str, Any] = {
    "interpreted": check_body("system.REQUEST('date')"),
    "queued": sandboxed(check_body("system.REQUEST('time')")),
    "unknown call": check_body("system.REQUESTS('city')"),
    "missing field": {"calls": ["system.REQUEST('date')"]},
    "wrong type": {**check_body(), "calls": "system.REQUEST('date')"},
    "not json": b"{not json",
    "empty": b"",
    "nested": b"[" * 20_000 + b"]" * 20_000,
    "not utf-8": b'{"spec": "\xff\xfe"}',
}


@pytest.mark.parametrize("name", list(BODIES))
def test_every_answer_is_the_one_fastapis_handler_gives(stack: Stack, keys: dict[str, str], name: str) -> None:
    body = BODIES[name]
    content = body if isinstance(body, bytes) else httpx.Request("POST", "/", json=body).content
    headers = {"Content-Type": "application/json"}
    with client_for(stack, keys["acme"]) as acme:
        short = acme.post("/check-actions", content=content, headers=headers, params={"wait": 30})
        long = acme.post("/check-actions", content=content, headers=headers, params={"wait": 30, "via": "fastapi"})
    _same(short, long)
    if name in ("interpreted", "queued"):
        assert short.status_code == 200
    elif name in ("unknown call", "missing field", "wrong type"):
        assert short.status_code == 422 and short.json()["error"]["field"], short.text


def test_a_cached_check_is_answered_by_its_digest_as_the_first_time_and_per_tenant(
    stack: Stack, keys: dict[str, str],
) -> None:
    body = sandboxed(check_body("system.REQUEST('party_size')"))
    with client_for(stack, keys["acme"]) as acme, client_for(stack, keys["globex"]) as globex:
        first = acme.post("/check-actions", json=body, params={"wait": 30})
        again = [acme.post("/check-actions", json=body, params=params) for params in ({"wait": 30}, {}, {"wait": 0})]
        other = globex.post("/check-actions", json=body, params={"wait": 30})
    assert first.status_code == 200 and first.json()["judged_by"] == "sandbox", first.text
    for answer in again:
        _same(answer, first)
    assert other.status_code == 200 and other.headers["X-Job-Id"] != first.headers["X-Job-Id"]
    assert other.json() == first.json()  # the same verdicts, from the other tenant's own job


def test_a_request_handed_on_takes_one_token_and_counts_one_failure(stack: Stack, keys: dict[str, str]) -> None:
    """`limited` sends bodies FastAPI's handler answers (422): after BURST of them the tenant is refused, not
    after half as many. A wrong key is refused 401 three times (the failures' burst), then 429."""
    with client_for(stack, keys["limited"]) as limited:
        answers = [limited.post("/check-actions", json=BODIES["wrong type"]).status_code for _ in range(BURST + 1)]
    assert answers[:BURST] == [422] * BURST and answers[BURST] == 429, answers
    with client_for(stack, "pk_wrong") as wrong:
        refused = [wrong.post("/check-actions", json=check_body()).status_code for _ in range(4)]
    assert refused == [401, 401, 401, 429], refused


def test_only_a_plain_wait_is_read_by_the_short_way() -> None:
    assert plain_wait(b"") == (True, None)
    assert plain_wait(b"wait=2.5") == (True, 2.5)
    for query in (b"wait=-1", b"wait=1e3", b"wait=nan", b"wait=1&wait=2", b"via=x", b"wait=", b"wait=1&x=2"):
        assert plain_wait(query) == (False, None), query


def test_the_memo_keeps_each_tenant_apart_and_bounded() -> None:
    memo = CheckMemo(per_tenant=2)
    memo.put("a", b"1", Known("job-1", "key-1"))
    assert memo.get("b", b"1") is None
    memo.put("a", b"2", Known("job-2", "key-2"))
    assert memo.get("a", b"1") == Known("job-1", "key-1")  # now the most recently used
    memo.put("a", b"3", Known("job-3", "key-3"))
    assert memo.get("a", b"2") is None and memo.get("a", b"1") is not None
    for n in range(10):
        memo.put("b", str(n).encode(), Known("x", "y"))
    assert memo.get("a", b"3") is not None  # another tenant's requests push out none of a's
