"""CPU-heavy request handling off the event loop: a request's programs are parsed and checked in processes.

`ast.parse` is C code that holds the GIL for its whole run (a 200 KB program takes 0.2-1 s on the 2-core
development box), so a thread would not keep the loop free: every other client, `/health` included, would
wait. A small process pool does the parsing, checking and history rendering of every request whose program
text is larger than `INLINE_CHARS` (smaller ones cost less than the round trip). Each tenant has at most
`per_tenant` requests in the pool at once (the rest wait in the tenant's own line), so one tenant's heavy
requests cannot take the pool from the others.

This module imports only the standard library and `programs` at its top: the pool's processes import it.
"""

from __future__ import annotations

import asyncio
import json
import logging
import multiprocessing
import os
import re
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, NamedTuple, TypeVar

from precond.convert.openai import call_lines, structured_history
from precond.jobs.lifetime import die_with_parent
from precond.programs import checks

log = logging.getLogger("precond.gateway")
INLINE_CHARS = 16_000
"""Program text (spec, demonstrations, history) checked on the event loop: a few milliseconds at most."""
T = TypeVar("T")


MAX_JSON_VALUES = 100_000
"""JSON values (objects, arrays, scalars, keys) of one body. A real 4 MB request is a few large strings; 400,000
tiny members are only work (pydantic made an error object of each, and the gateway grew by 465 MiB)."""
INLINE_BODY_BYTES = 64 * 1024
"""Bodies parsed on the event loop; larger ones in the pool (`json.loads` holds the GIL too)."""


def _too_many_values(value: Any) -> bool:
    count, todo = 0, [value]
    while todo:
        item = todo.pop()
        count += 1 + (len(item) if isinstance(item, dict) else 0)
        if count > MAX_JSON_VALUES:
            return True
        if isinstance(item, dict):
            todo.extend(item.values())
        elif isinstance(item, list):
            todo.extend(item)
    return False


def parsed_json(body: bytes) -> Any:
    """The body as JSON; a `(message, position)` tuple when it is not JSON, `None` when it has too many values.
    (A parsed body comes back as a list holding it, so that a body that is itself a JSON tuple-like array or
    null is never mistaken for one of those.)"""
    try:
        value = json.loads(body)
    except json.JSONDecodeError as exc:
        return (exc.msg, exc.pos)
    except (ValueError, RecursionError) as exc:
        return (type(exc).__name__, 0)
    return None if _too_many_values(value) else [value]


class PoolBroken(RuntimeError):
    """A check process died (the pool is replaced); the request may be retried."""


def problem_of(check: Callable[..., object], *args: Any) -> checks.Problem | None:
    """Run a static check; its ProgramProblem as a Problem (exceptions with a custom __init__ do not cross a
    process boundary), and a recursion overflow anywhere in it as a 422 rather than a 500."""
    try:
        check(*args)
    except checks.ProgramProblem as exc:
        return exc.problem
    except RecursionError:
        return checks.too_deep("body").problem
    return None


RENDER_SPEEDUP = 4
"""How much cheaper a character of a structured history (JSON) is to render than a character of a program is to
parse: rendering reads about 47 KB/ms, `ast.parse` about 9.5 KB/ms (Intel Xeon with avx512, the airline
histories of bench/tool_check_bench.py). An agent's 20 KB of messages then render on the loop (0.5 ms)
instead of paying the pool's round trip."""


def rendering_chars(spec: str, history_json_chars: int) -> int:
    """What rendering a structured history costs, in characters of program text parsed (`CheckPool.run`)."""
    return len(spec) + history_json_chars // RENDER_SPEEDUP


def rendered(spec: str, history: Sequence[Mapping[str, Any]], tag: str, max_chars: int) -> str | checks.Problem:
    """A structured history's program (events or OpenAI messages), or why it cannot be one (`tag`: the caller's,
    under which the spec's reading is remembered). The program is bounded here, where the body is accepted, by
    the bound of a history sent as code (`max_chars`): a worker re-reads the job under that bound, so a longer
    one would be accepted here and fail there."""
    try:
        program = structured_history(spec, history, scope=tag)
    except checks.ProgramProblem as exc:
        return exc.problem
    except RecursionError:
        return checks.too_deep("history").problem
    if len(program) > max_chars:
        longest = max(range(len(history)), key=lambda n: len(json.dumps(history[n], default=str)))
        return checks.Problem("invalid_input", "history", (
            f"the history renders to a program of {len(program):,} characters, over the {max_chars:,} a history "
            f"may have (as code or as events): send fewer or shorter events (the longest is history[{longest}])"))
    return program


def rendered_calls(spec: str, calls: Sequence[str | Mapping[str, Any]], tag: str) -> list[str] | checks.Problem:
    """Proposed calls as program lines (`{"name", "arguments"}` rendered over the spec's tools), or why they
    cannot be (`tag`: the caller's, under which the spec's reading is remembered)."""
    try:
        return call_lines(spec, calls, scope=tag)
    except checks.ProgramProblem as exc:
        return exc.problem
    except RecursionError:
        return checks.too_deep("calls").problem


def labelled_run(spec: str, history: str | Sequence[Mapping[str, Any]], call: str | Mapping[str, Any], tag: str,
                 max_chars: int) -> tuple[str, int, str] | checks.Problem:
    """A judged call as a run of its own: the history's program (rendered and bounded as `/check-actions`
    renders it) with the call as its last line, that line, and the action it calls; or why it cannot be one (a
    history that does not parse, a call that is no call of one of the spec's actions). Parsed, never run."""
    program = history if isinstance(history, str) else rendered(spec, history, tag, max_chars)
    lines = rendered_calls(spec, [call], tag)
    if isinstance(program, checks.Problem) or isinstance(lines, checks.Problem):
        return program if isinstance(program, checks.Problem) else lines  # type: ignore[return-value]
    try:
        checks.check_check(spec, {}, program, lines, tag)
        _, methods = checks.remembered_spec_methods(tag, spec)
        receivers = checks.history_receivers(tag, checks.spec_classes(methods), program)
    except checks.ProgramProblem as exc:
        return checks.Problem(exc.problem.type, exc.problem.field.replace("calls[0]", "call"), exc.problem.message)
    except RecursionError:
        return checks.too_deep("history").problem
    action = checks.called_action(methods, receivers, lines[0])
    if action is None or not methods[action].stub:
        return checks.Problem("invalid_input", "call", f"{lines[0][:200]!r} is not a call of one of the spec's "
                              "actions on an object the history creates")
    run = f"{program.rstrip()}\n{lines[0]}\n" if program.strip() else f"{lines[0]}\n"
    if len(run) > max_chars:
        return checks.Problem("invalid_input", "history", f"the history and the call make a program of "
                              f"{len(run):,} characters, over {max_chars:,}")
    return run, len(run.splitlines()), action


ITERATING = re.compile(r"\bfor\b|\b(?:all|any|max|min|sum)\s*\(|[*+-]")
"""What makes a rule's evaluation grow with more than the collections it reads: a comprehension, a call that walks
its arguments, arithmetic that builds a sequence (`slot * 100000`). The interpreter bounds each call's rules at
`rule_interpreter.MAX_STEPS` (some 0.1 s), which the event loop must never spend: a check with such a rule is
screened and judged in the pool, in the tenant's line. (Read from the text, so a `-` in a date sends a rule there
too: never the other way round.)"""


def iterating_rules(preconditions: Mapping[str, Sequence[str]]) -> bool:
    return any(ITERATING.search(rule) for rules in preconditions.values() for rule in rules)


class Judged(NamedTuple):
    """A check's answer, judged in the gateway (`interpreted`)."""

    answer: dict[str, Any]


class Queued(NamedTuple):
    """A check for the sandbox: the history's program and the calls' lines of the job the worker runs."""

    program: str
    lines: list[str]


def screened_check(spec: str, preconditions: Mapping[str, Sequence[str]], decided: Mapping[str, Mapping[str, str]],
                   history: str | Sequence[Mapping[str, Any]], calls: Sequence[str | Mapping[str, Any]], tag: str,
                   max_chars: int, interpret: bool = True) -> Judged | Queued | checks.Problem:
    """All the gateway does to a check before it answers or queues it, in one trip to the pool: the history and
    the calls rendered to program text (`rendered`, `rendered_calls`), the static screen (`checks.check_check`:
    the worker does not repeat it), and the answer itself where no caller text is code to run
    (`interpreted.judged`), unless `interpret` is off; `tag`: the caller's, under which what is read is
    remembered."""
    program = history if isinstance(history, str) else rendered(spec, history, tag, max_chars)
    if isinstance(program, checks.Problem):
        return program
    lines = rendered_calls(spec, calls, tag)
    if isinstance(lines, checks.Problem):
        return lines
    problem = problem_of(checks.check_check, spec, preconditions, program, lines, tag)
    if problem is not None:
        return problem
    if not interpret:
        return Queued(program, lines)
    from precond.gateway import interpreted  # here, not at the top: a pool process imports it on its first check

    try:
        answer = interpreted.judged(spec, preconditions, decided, history, program, calls, lines, tag)
    except RecursionError:
        answer = None  # a history nested too deeply for the interpreter: the sandbox judges it
    return Judged(answer) if answer is not None else Queued(program, lines)


CHECK_NICENESS = 10


def _start_check_process(gateway: int) -> None:
    """A check process runs below the gateway's priority: parsing one tenant's megabytes must not take the CPU
    from the event loop that answers everyone else (and `/health`) on a machine with few cores. It ends with its
    gateway, however the gateway ends (precond/jobs/lifetime.py)."""
    die_with_parent(gateway)
    os.nice(CHECK_NICENESS)


class CheckPool:
    def __init__(self, processes: int, per_tenant: int) -> None:
        self.processes, self.per_tenant = processes, per_tenant
        self._executor = self._start()
        self._lines: dict[str, asyncio.Semaphore] = {}  # one per tenant tag (tenants are bounded by the keys file)

    def _start(self) -> ProcessPoolExecutor:
        # spawn: a fresh interpreter that imports only this module, never a fork of the gateway's threads
        return ProcessPoolExecutor(self.processes, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_start_check_process, initargs=(os.getpid(),))

    async def run(self, tag: str, chars: int, function: Callable[..., T], *args: Any) -> T:
        """`function(*args)` on the loop when the request is small (`chars`: its cost in characters of program
        text parsed), else in the pool in the tenant's line."""
        if chars <= INLINE_CHARS:
            return function(*args)
        line = self._lines.setdefault(tag, asyncio.Semaphore(self.per_tenant))
        async with line:
            try:
                return await asyncio.get_running_loop().run_in_executor(self._executor, function, *args)
            except BrokenProcessPool:
                log.error("a check process died; replacing the pool")
                self._executor.shutdown(wait=False, cancel_futures=True)
                self._executor = self._start()
                raise PoolBroken("a check process died; retry the request") from None

    def close(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)
