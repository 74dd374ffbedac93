"""`AsyncClient`: the asyncio client (httpx). The blocking `Client` (sync.py) is written from this file by
`scripts/unasync_client.py`: edit this one."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterable, Mapping
from types import TracebackType
from typing import Any

import httpx
from pydantic import BaseModel

from precond_client import _core
from precond_client.errors import JobTimeout, PrecondError
from precond_client.schemas import (
    CheckRequest,
    CheckResponse,
    InferOptions,
    InferRequest,
    InferResponse,
    JobStatus,
    NextActionOptions,
    NextActionRequest,
    NextActionResponse,
    PreconditionSet,
    PreconditionSetCreate,
    PreconditionSetList,
    RuleEdit,
)
from precond_client.schemas.training import PolicyAdapter, PolicyAdapterList, TrainPolicyRequest

RequestLike = BaseModel | Mapping[str, Any]


class AsyncClient:
    """An asyncio client of the precondition service; every method of `Client`, awaited.

    >>> async with AsyncClient("http://127.0.0.1:8000", api_key="pk_...") as client:
    ...     verdicts = await client.check_actions(request)

    Each operation takes its request model (or a dict with the same fields), waits up to `wait` seconds on
    the server, follows a 202 by polling `GET /jobs/{id}` (calling `progress` with the job's status) until the
    job is done or `timeout` passes, and returns the typed response. 429 and 503 answers and transport errors
    are retried per `retry`; what remains is raised as a `PrecondError` subclass.
    """

    def __init__(
        self,
        base_url: str,
        api_key: str | None = None,
        *,
        timeout: float = 60.0,
        retry: _core.Retry | None = None,
        polling: _core.Polling | None = None,
        on_retry: _core.RetryHook | None = None,
        http: httpx.AsyncClient | None = None,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.retry = retry or _core.Retry()
        self.polling = polling or _core.Polling()
        self.on_retry = on_retry
        self._http = http or httpx.AsyncClient(base_url=self.base_url, timeout=timeout)
        self._headers = _core.headers(api_key)

    # the operations -----------------------------------------------------------------------------------------

    async def infer_preconditions(
        self, request: InferRequest | Mapping[str, Any], *, wait: float | None = None,
        progress: _core.Progress | None = None, timeout: float | None = None,
    ) -> InferResponse:
        body, _ = _core.operation(request, InferRequest)
        return await self._follow(body, InferResponse, wait, progress, timeout)

    async def next_action(
        self, request: NextActionRequest | Mapping[str, Any], *, wait: float | None = None,
        progress: _core.Progress | None = None, timeout: float | None = None,
    ) -> NextActionResponse:
        body, _ = _core.operation(request, NextActionRequest)
        return await self._follow(body, NextActionResponse, wait, progress, timeout)

    async def check_actions(
        self, request: CheckRequest | Mapping[str, Any], *, wait: float | None = None,
        progress: _core.Progress | None = None, timeout: float | None = None,
    ) -> CheckResponse:
        body, _ = _core.operation(request, CheckRequest)
        return await self._follow(body, CheckResponse, wait, progress, timeout)

    # precondition sets and structured histories -------------------------------------------------------------

    async def create_set(self, request: PreconditionSetCreate | Mapping[str, Any]) -> PreconditionSet:
        """Store rules as version 1 of a new set (`spec`, `preconditions`, `demonstrations`; an inference's
        `preconditions` as returned). A rule that blocks a demonstrated call is `InvalidInput` (type
        `blocks_demonstration`) unless `force`."""
        body = _core.set_body(_core.validated(request, PreconditionSetCreate))
        answer = await self._send("POST", "/precondition-sets", json=body)
        return PreconditionSet.model_validate(answer.json())

    async def list_sets(self, *, offset: int = 0, limit: int = 20) -> PreconditionSetList:
        """The tenant's sets, newest first, each with how many rules are assumed, zero-shot or without evidence;
        `next_offset` pages on."""
        answer = await self._send("GET", "/precondition-sets", params={"offset": offset, "limit": limit})
        return PreconditionSetList.model_validate(answer.json())

    async def get_set(self, reference: str) -> PreconditionSet:
        """A set's latest version (`id`) or a given one (`id@version`); `NotFound` for none of yours."""
        return PreconditionSet.model_validate((await self._send("GET", _core.set_path(reference))).json())

    async def edit_set(
        self, set_id: str, edits: Iterable[RuleEdit | Mapping[str, Any]], *, base_version: int | None = None,
        force: bool = False,
    ) -> PreconditionSet:
        """A new version by edits (`precond_client.rules`: `add`, `remove`, `require`, `reject`); `Conflict` when
        `base_version` is no longer the latest, `InvalidInput` (`blocks_demonstration`) unless `force`."""
        body = _core.edit_body(edits, base_version, force)
        answer = await self._send("POST", _core.set_path(set_id, "/versions"), json=body)
        return PreconditionSet.model_validate(answer.json())

    async def reinfer_set(
        self, set_id: str, demonstrations: Iterable[str], *, actions: Iterable[str] | None = None,
        options: InferOptions | Mapping[str, Any] | None = None,
        base_version: int | None = None, force: bool = False, wait: float | None = None,
        progress: _core.Progress | None = None, timeout: float | None = None,
    ) -> PreconditionSet:
        """Re-infer the set from its demonstrations and these (a job, followed like every operation): the new
        version keeps required rules, never brings back rejected ones, and carries `diff` against its base.
        `InvalidInput` (`blocks_demonstration`, `field` naming `demonstrations[i]`) when a new demonstration
        breaks a required rule, unless `force`; `Conflict` when the set got a newer version meanwhile."""
        body = _core.reinfer_body(demonstrations, actions, options, base_version, force)
        params = {} if wait is None else {"wait": wait}
        answer = await self._send("POST", _core.set_path(set_id, "/reinfer"), json=body, params=params)
        status = await self._poll(_core.submitted(answer, "reinfer"), progress, timeout)
        return _core.result(status, PreconditionSet)

    # trained policies -------------------------------------------------------------------------------------------

    async def train_policy(
        self, request: TrainPolicyRequest | Mapping[str, Any], *, adapter: str | None = None,
        wait: float | None = None, progress: _core.Progress | None = None, timeout: float | None = None,
    ) -> PolicyAdapter:
        """Fine-tune the code model on the request's demonstrations (a job on the training queue, minutes,
        followed like every operation; `cancel` its job and nothing is stored) and store the adapter: version 1
        of a new trained policy, or with `adapter` (an id) that policy's next version. `next_action` then names
        it with `options.policy = f"adapter:{policy.id}"` (or `policy.reference` for this version)."""
        body = _core.validated(request, TrainPolicyRequest).model_dump(mode="json")
        path = "/policies" if adapter is None else _core.policy_path(adapter, "/versions")
        params = {} if wait is None else {"wait": wait}
        answer = await self._send("POST", path, json=body, params=params)
        status = await self._poll(_core.submitted(answer, "train-policy"), progress, timeout)
        return _core.result(status, PolicyAdapter)

    async def list_policies(self) -> PolicyAdapterList:
        """The tenant's trained policies (the latest version of each) and the bytes they take."""
        return PolicyAdapterList.model_validate((await self._send("GET", "/policies")).json())

    async def get_policy(self, reference: str) -> PolicyAdapter:
        """A trained policy's latest version (`id`) or a given one (`id@version`); `NotFound` for none of yours."""
        return PolicyAdapter.model_validate((await self._send("GET", _core.policy_path(reference))).json())

    async def delete_policy(self, adapter_id: str) -> None:
        """Delete a trained policy with all its versions; `NotFound` for none of yours."""
        await self._send("DELETE", _core.policy_path(adapter_id))

    async def check_with_set(
        self, precondition_set: str, history: _core.HistoryLike, calls: Iterable[_core.CallLike], *,
        wait: float | None = None,
        progress: _core.Progress | None = None, timeout: float | None = None,
    ) -> CheckResponse:
        """`check_actions` with a stored set (`id` or `id@version`) and a history of events (`History`), or of
        an agent's OpenAI chat messages with tool calls `{"name", "arguments"}` as `calls`."""
        body = _core.check_body(precondition_set, history, calls)
        return await self.check_actions(body, wait=wait, progress=progress, timeout=timeout)

    async def next_action_with_set(
        self, precondition_set: str, history: _core.HistoryLike, *, demonstrations: Iterable[str] = (),
        options: NextActionOptions | Mapping[str, Any] | None = None, wait: float | None = None,
        progress: _core.Progress | None = None, timeout: float | None = None,
    ) -> NextActionResponse:
        """`next_action` with a stored set and a history of events."""
        body = _core.next_action_body(precondition_set, history, demonstrations, options)
        return await self.next_action(body, wait=wait, progress=progress, timeout=timeout)

    async def submit(self, request: BaseModel, *, wait: float | None = 0) -> JobStatus:
        """Send a request (a request model) without following it: its job's status (`succeeded` with the
        result when it was done within `wait` or cached). Follow it with `result(job_id)`, stop it with
        `cancel(job_id)`."""
        body, op = _core.operation(request, type(request))
        params = {} if wait is None else {"wait": wait}
        answer = await self._send("POST", op.path, json=body.model_dump(mode="json"), params=params)
        return _core.submitted(answer, op.kind)

    async def result(
        self, job_id: str, *, progress: _core.Progress | None = None, timeout: float | None = None
    ) -> BaseModel:
        """Poll a job until it is done: its typed response, or its error raised."""
        status = await self._poll(await self.job(job_id), progress, timeout)
        return _core.result(status, _core.RESPONSES[status.kind])

    async def job(self, job_id: str) -> JobStatus:
        return JobStatus.model_validate((await self._send("GET", f"/jobs/{job_id}")).json())

    async def cancel(self, job_id: str) -> JobStatus:
        """Cancel a queued or running job (a finished one is returned unchanged)."""
        return JobStatus.model_validate((await self._send("DELETE", f"/jobs/{job_id}")).json())

    async def health(self) -> dict[str, Any]:
        """Liveness, and whether the workers run untrusted code confined (`sandbox`). No key needed."""
        body: dict[str, Any] = (await self._send("GET", "/health")).json()
        return body

    async def ready(self) -> dict[str, Any]:
        """Readiness (Redis up, a worker that confines untrusted code with its model loaded); `Unavailable`
        when not ready. Asked once, never retried: a probe reports, it does not wait."""
        body: dict[str, Any] = (await self._send("GET", "/ready", retries=False)).json()
        return body

    # plumbing -----------------------------------------------------------------------------------------------

    async def _follow(
        self, body: BaseModel, expected: type[_core.Req], wait: float | None, progress: _core.Progress | None,
        timeout: float | None,
    ) -> _core.Req:
        status = await self.submit(body, wait=wait)
        status = await self._poll(status, progress, timeout)
        return _core.result(status, expected)

    async def _poll(self, status: JobStatus, progress: _core.Progress | None, timeout: float | None) -> JobStatus:
        deadline = None if timeout is None else time.monotonic() + timeout
        polls = 0
        while not _core.finished(status):
            if progress is not None:
                progress(status)
            if deadline is not None and time.monotonic() >= deadline:
                raise JobTimeout(f"job {status.id} not done after {timeout} s ({status.status})", job_id=status.id)
            await asyncio.sleep(self.polling.interval(polls))
            polls += 1
            status = await self.job(status.id)
        if progress is not None:
            progress(status)
        return status

    async def _send(self, method: str, path: str, *, retries: bool = True, **kwargs: Any) -> httpx.Response:
        attempts = self.retry.attempts if retries else 1
        for attempt in range(attempts):
            error: PrecondError
            try:
                response = await self._http.request(method, path, headers=self._headers, **kwargs)
            except httpx.TransportError as exc:
                error = _core.transport_error(exc, self.base_url + path)
                after = None
            else:
                if response.status_code < 400:
                    return response
                error = _core.error_from_response(response)
                if response.status_code not in _core.RETRY_STATUSES:
                    raise error
                after = _core.retry_after(response)
            if attempt + 1 >= attempts:
                raise error
            delay = self.retry.delay(attempt, after)
            if self.on_retry is not None:
                self.on_retry(error, delay)
            await asyncio.sleep(delay)
        raise AssertionError("unreachable")  # pragma: no cover

    async def close(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, value: BaseException | None, traceback: TracebackType | None
    ) -> None:
        await self.close()
