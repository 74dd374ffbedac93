"""Bounds a user meets at the gateway: a history sent as events is bounded where the body is accepted, by the
bound of a history sent as code (one that renders to more is a 422 naming `history`, never a job that a worker
then refuses with a 500); a `?wait=` over the server's cap is cut to it, and the 202 says so."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from precond.stack.local import Stack, example, heavy_infer_body, make_stack, serving
from precond_client import Client
from precond_client.schemas import MAX_SOURCE_CHARS


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[Stack]:
    stack = make_stack(tmp_path_factory.mktemp("bounds"), tiny_model_dir,
                       PRECOND_MAX_BODY_BYTES=str(2 * 1024 * 1024), PRECOND_WAIT_MAX_S="0.5")
    with serving(stack, workers=1):
        yield stack


def _events(*sizes: int) -> list[dict[str, Any]]:
    opening = [{"actor": "user", "act": "INFORM_INTENT", "args": ["FindRestaurants"]}]
    return opening + [{"actor": "user", "act": "INFORM", "args": ["x" * size]} for size in sizes]


@pytest.mark.parametrize("sizes", [(250_000,), (80_000, 80_000, 80_000)], ids=["one-250KB", "three-80KB"])
@pytest.mark.parametrize("route", ["/check-actions", "/next-action"])
def test_an_event_history_over_the_bound_is_a_422_naming_it(stack: Stack, route: str, sizes: tuple[int, ...]) -> None:
    body = example("check-actions" if route == "/check-actions" else "next-action")
    body["history"] = _events(*sizes)
    with stack.http() as client:
        answer = client.post(route, json=body, params={"wait": 30})
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["field"] == "history", error
    assert f"{MAX_SOURCE_CHARS:,}" in error["message"] and "history[" in error["message"], error
    assert "pydantic" not in answer.text and "validation error" not in answer.text.lower()


def test_an_event_history_within_the_bound_is_judged(stack: Stack) -> None:
    body = example("check-actions")
    body["history"] = _events(60_000, 60_000)
    with stack.http() as client:
        answer = client.post("/check-actions", json=body, params={"wait": 30}, timeout=60)
    assert answer.status_code == 200, answer.text


def test_a_code_history_over_the_bound_is_the_same_field(stack: Stack) -> None:
    body = example("check-actions")
    body["history"] = "user = USER()\n" + "#" * MAX_SOURCE_CHARS
    with stack.http() as client:
        answer = client.post("/check-actions", json=body, params={"wait": 30})
    assert answer.status_code == 422 and answer.json()["error"]["field"] == "history", answer.text


def test_a_202_states_the_wait_cap_and_the_client_follows_the_job(stack: Stack) -> None:
    body = heavy_infer_body(seed=46, millions=20)
    with stack.http() as client:
        accepted = client.post("/infer-preconditions", json=body, params={"wait": 300})
    assert accepted.status_code == 202, accepted.text
    assert accepted.headers["X-Wait-Max-S"] == "0.5" and accepted.json()["wait_max_s"] == 0.5
    with Client(stack.base_url) as following:  # the same request: the client polls the job to its end
        answer = following.infer_preconditions(body, wait=300)
    assert "SYSTEM.GOODBYE" in answer.preconditions
