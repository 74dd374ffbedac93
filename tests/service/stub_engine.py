"""A torch-free, sandbox-free engine for service tests, plugged in with PRECOND_ENGINE_FACTORY.

The service is tested for queueing, caching, failure and cancellation behaviour, not for inference quality.
The spec is still parsed by the real `worker.spec` (pure ast), so bad specs fail with the engine's own errors.
A spec containing `# slow: <seconds>` makes a job last that long, polling its cancel predicate meanwhile.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable

from schemas.api import (
    CallVerdict,
    CheckRequest,
    CheckResponse,
    InferRequest,
    InferResponse,
    InferStats,
    NextActionRequest,
    NextActionResponse,
    StageCounts,
)
from schemas.errors import Cancelled
from worker.spec import parse_spec, resolve_actions

ProgressFn = Callable[[str, int, int], None]


def _linger(spec: str, progress: ProgressFn | None, cancelled: Callable[[], bool] | None) -> None:
    match = re.search(r"# slow: ([0-9.]+)", spec)
    seconds = float(match.group(1)) if match else 0.0
    steps = max(1, int(seconds / 0.05))
    for step in range(steps):
        if cancelled and cancelled():
            raise Cancelled("job cancelled")
        if progress:
            progress("generate", step, steps)
        time.sleep(seconds / steps)


class StubEngine:
    model_loaded = True

    def model(self) -> object:
        return object()

    def infer(
        self,
        request: InferRequest,
        progress: ProgressFn | None = None,
        cancelled: Callable[[], bool] | None = None,
    ) -> InferResponse:
        actions = resolve_actions(parse_spec(request.spec), request.actions)
        if progress:
            progress("trace", 0, len(request.demonstrations))
        _linger(request.spec, progress, cancelled)
        counts = {action: StageCounts() for action in actions}
        stats = InferStats(actions=counts, total=StageCounts(), seconds={"trace": 0.0})
        return InferResponse(
            preconditions={a: [] for a in actions}, program=request.spec, candidates={}, stats=stats
        )

    def next_action(
        self,
        request: NextActionRequest,
        progress: ProgressFn | None = None,
        cancelled: Callable[[], bool] | None = None,
    ) -> NextActionResponse:
        parse_spec(request.spec)
        _linger(request.spec, progress, cancelled)
        return NextActionResponse(actions=[])

    def check(self, request: CheckRequest) -> CheckResponse:
        parse_spec(request.spec)
        return CheckResponse(results=[CallVerdict(call=call, allowed=True) for call in request.calls])


def build() -> StubEngine:
    return StubEngine()
