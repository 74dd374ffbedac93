"""A pre-forked child: confine, warm up, wait for its request, run it, exit without cleanup; or, when the
server keeps it for its scope's next request (`keep`), wait for that one instead of exiting."""

from __future__ import annotations

import collections
import gc
import json
import os
import sys
import typing
import warnings

from . import runtime
from .boundary import REQUEST_FD, RESULT_FD, BoundaryError, confine
from .check import job_check
from .evaluate import job_evaluate
from .framing import Reporter, read_request
from .trace import job_trace
from .values import Failure, OutputLimit, describe

BOUNDARY_FAILED = 71  # exit code: the child could not be confined and ran nothing

JOBS: dict[str, typing.Callable[[dict[str, typing.Any], runtime.Context], dict[str, object]]] = {
    "trace": job_trace, "evaluate": job_evaluate, "check": job_check,
}

_WARM_UP = {
    "spec": "from collections import defaultdict\n"
            "class A:\n    def __init__(self):\n        self.d = defaultdict(bool)\n"
            "    def f(self, x):\n        self.d[x] = True\n    def g(self, x):\n        pass\n",
    "demonstrations": ["a = A()\na.f('x')\na.g('y')\n"],
    "candidates": {"A.g": ["self.d[x]", "not self.d[x] or x in self.d"]},
    "history": "a = A()\na.f('x')\n",
    "preconditions": {"A.g": ["self.d[x]"]},
    "calls": [{"target": "a", "method": "g", "args": ["x"], "kwargs": {}}],
}


def run_child(config: dict[str, typing.Any], workdir: str, was_root: bool, bpf: bytes | None) -> typing.NoReturn:
    limits = config["limits"]
    try:
        confine(limits, workdir, was_root, bpf)
    except (BoundaryError, OSError):
        os._exit(BOUNDARY_FAILED)
    budget = _conveniences(limits)
    table = runtime.restricted_builtins(frozenset(config["allowed_imports"]))
    _warm_up(table)
    gc.freeze()  # what start-up made lives as long as the child: a collection between requests skips it (1.3 ms)
    while (received := read_request(REQUEST_FD)) is not None:
        settled, body = received
        _answer(json.loads(body), settled, table, limits, budget)
        if settled.get("keep") is not True:
            break
        budget[0] = int(limits["output_bytes"])  # each request has the whole output budget
        gc.collect()  # collection is off while untrusted code runs; between requests it is off the latency
    os._exit(0)


def _answer(request: dict[str, typing.Any], settled: dict[str, typing.Any], table: dict[str, object],
            limits: dict[str, typing.Any], budget: list[int]) -> None:
    report = Reporter(RESULT_FD, int(limits["result_bytes"]))
    ctx = runtime.Context(table, report, frozenset(settled["skip"]))
    try:
        result = JOBS[request["op"]](request["payload"], ctx)
    except Failure as failure:
        result = {"error": failure.info}
    except MemoryError:
        result = {"error": {"kind": "limit", "limit": "memory", "message": "memory limit exceeded"}}
    except OutputLimit:
        result = {"error": {"kind": "limit", "limit": "output", "message": "output limit exceeded"}}
    except RecursionError:
        result = {"error": {"kind": "limit", "limit": "recursion", "message": "maximum recursion depth"}}
    except BaseException as exc:
        name, message = describe(exc)
        result = {"error": {"kind": "internal", "message": f"{name}: {message}"}}
    if budget[0] < 0:
        result = {"error": {"kind": "limit", "limit": "output", "message": "output limit exceeded"}}
    report.end(result)


def _conveniences(limits: dict[str, typing.Any]) -> list[int]:
    """Readable errors instead of kernel refusals; nothing here is a protection."""
    budget = runtime.quiet_output(int(limits["output_bytes"]))
    warnings.simplefilter("ignore")
    gc.disable()
    sys.setrecursionlimit(runtime.stack_depth() + int(limits["recursion"]))
    collections.defaultdict = runtime.UndoDefaultDict  # type: ignore[misc]
    return budget


def _warm_up(table: dict[str, object]) -> None:
    """Run every job once on trusted input while waiting for the request: a fresh fork pays copy-on-write
    faults and lazy initialisation on first use, and this moves that cost off the request's latency."""
    ctx = runtime.Context(table, Reporter(None, 0))
    for job in JOBS.values():
        json.dumps(job(dict(_WARM_UP), ctx))
