"""`precond mcp` (a recording, judging proxy in front of MCP servers: docs/mcp.md) and `precond label` (a call
of a recorded session marked allowed or not: the counterexamples of the set's next version). Bad input exits 2
naming the option or the record."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from pydantic import TypeAdapter, ValidationError

from precond.cli.engine_commands import ApiKey, _decided_of
from precond.convert.shape import ConvertError, parse_json

MODES = ("record", "enforce", "shadow")
PRECONDITIONS: TypeAdapter[dict[str, list[str]]] = TypeAdapter(dict[str, list[str]])


def _fail(message: str) -> NoReturn:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


def _read(path: Path, option: str) -> Any:
    try:
        return parse_json(path.read_text(encoding="utf-8"), f"{option} {path}")
    except OSError as exc:
        _fail(f"{option}: cannot read {path}: {exc.strerror}")
    except UnicodeDecodeError as exc:
        _fail(f"{option} {path}: not UTF-8: {exc.reason}")
    except ConvertError as exc:
        _fail(str(exc))


def _rules_judge(path: Path) -> Any:
    """`--rules`: what `precond infer` prints (or `{action: [rules]}`), judged by the embedded guard over the spec
    `precond convert openai` writes from the upstreams' tools (its actions being the tools it counts as writes)."""
    from precond_client.guard import Guard, NotEmbeddable
    from precond_client.mcp.serve import StartError
    from precond_client.mcp.tools import spec_for

    loaded = _read(path, "--rules")
    try:
        preconditions = PRECONDITIONS.validate_python(
            loaded.get("preconditions", loaded) if isinstance(loaded, dict) else loaded)
    except ValidationError as exc:
        _fail(f"--rules {path}: not rules per action (an inference's answer or {{action: [rules]}}): "
              f"{exc.errors()[0]['msg']} at {'.'.join(map(str, exc.errors()[0]['loc']))}")
    decided = _decided_of(loaded)

    def make(schemas: Sequence[dict[str, Any]]) -> Guard:
        try:
            return Guard(spec_for(schemas), preconditions, decided, name=str(path))
        except NotEmbeddable as exc:
            raise StartError(f"--rules {path}: {exc}") from None
    return make


def mcp(
    upstream: Annotated[list[str], typer.Option(help="An MCP server to front: a command line (stdio), or an "
                                                "http(s):// URL (streamable HTTP). Repeatable.")],
    log: Annotated[Path, typer.Option(help="Folder for sessions/<session>.json (OpenAI messages, one record per "
                                      "MCP session), calls.jsonl (each call's verdict) and tools.json.")],
    mode: Annotated[str, typer.Option(help="record: forward and record; enforce: a refused call never reaches the "
                                      "upstream; shadow: judge and log, forward every call.")] = "record",
    rules: Annotated[Path | None, typer.Option(help="The rules: what `precond infer` prints (or a JSON object of "
                                               "action -> rules), judged in this process.", show_default=False)] = None,
    precondition_set: Annotated[str | None, typer.Option("--set", help="A stored set (ps_...@n), judged by the "
                                                         "service at --server.", show_default=False)] = None,
    server: Annotated[str | None, typer.Option(help="The service's URL, with --set.", envvar="PRECOND_SERVER",
                                               show_default=False)] = None,
    api_key: ApiKey = None,
    http: Annotated[int | None, typer.Option(min=1, max=65535, help="Serve streamable HTTP on "
                                             "http://127.0.0.1:PORT/mcp instead of stdio.", show_default=False)] = None,
    timeout: Annotated[float, typer.Option(min=0.1, max=3600, help="Seconds an upstream has to answer a call "
                                           "before the client gets an error naming it.")] = 30.0,
    start_timeout: Annotated[float, typer.Option(min=0.1, max=3600, help="Seconds an upstream has to start and "
                                                 "list its tools, at start and when a call starts it again after "
                                                 "its connection closed.")] = 120.0,
    max_log_bytes: Annotated[int, typer.Option(min=65536, help="Bound of one session's record: a call past it is "
                                               "refused, named.")] = 8 * 1024 * 1024,
    max_calls_bytes: Annotated[int, typer.Option(min=65536, help="Bound of calls.jsonl: a call past it is refused, "
                                                 "named, until the file is moved away.")] = 256 * 1024 * 1024,
) -> None:
    """Front MCP servers: list their tools unchanged, record every tool call, judge it with a set first."""
    if mode not in MODES:
        _fail(f"--mode: {mode!r} is not one of {', '.join(MODES)}")
    if rules is not None and precondition_set is not None:
        _fail("give --rules or --set, not both")
    judged = rules is not None or precondition_set is not None
    if mode == "record" and judged:
        _fail("--mode record judges nothing: give --mode enforce or shadow with --rules or --set")
    if mode != "record" and not judged:
        _fail(f"--mode {mode} needs the rules: --rules RESPONSE.json, or --set ps_...@n with --server URL")
    if precondition_set is not None and server is None:
        _fail("--set needs --server URL (the service that holds the set)")
    make = _rules_judge(rules) if rules is not None else _service_judge(precondition_set, server, api_key)
    _run(upstream, mode, log, http, (timeout, start_timeout), (max_log_bytes, max_calls_bytes), make)


def _service_judge(reference: str | None, server: str | None, api_key: str | None) -> Any:
    from precond_client.aio import AsyncClient
    from precond_client.guard import ServiceGuard

    def make(schemas: Sequence[dict[str, Any]]) -> ServiceGuard | None:
        if reference is None or server is None:
            return None
        return ServiceGuard(AsyncClient(server, api_key=api_key), reference)
    return make


def _run(upstreams: list[str], mode: str, log: Path, http: int | None, timeouts: tuple[float, float],
         bounds: tuple[int, int], make: Any) -> None:
    """The proxy on uvloop's event loop (as the gateway and the worker): the loop's turns, pipe reads and writes
    and the upstreams' processes are most of what a call costs the proxy beyond its own work."""
    import anyio

    from precond_client.mcp.serve import Settings, StartError, serve

    settings = Settings(upstreams, mode, log, http, timeout=timeouts[0], start_timeout=timeouts[1],  # type: ignore[arg-type]
                        max_log_bytes=bounds[0], max_calls_bytes=bounds[1])
    try:
        anyio.run(serve, settings, make, backend_options={"use_uvloop": True})
    except* StartError as group:
        _fail("; ".join(str(e) for e in _leaves(group)))
    except* OSError as group:
        _fail(f"--log {log}: {_leaves(group)[0]}")


def _leaves(group: BaseExceptionGroup[Any]) -> list[BaseException]:
    """The exceptions of a group of task groups' groups (each transport nests its own)."""
    return [leaf for e in group.exceptions
            for leaf in (_leaves(e) if isinstance(e, BaseExceptionGroup) else [e])]


def label(
    session: Annotated[Path, typer.Argument(metavar="SESSION.json", help="A session `precond mcp` recorded "
                                            "(sessions/<session>.json).")],
    call: Annotated[str, typer.Option(help="The call's id in that session (`call_3`, as calls.jsonl names it).")],
    labels: Annotated[Path, typer.Option(help="The labels file to add the record to (made if missing): "
                                         "`precond convert openai --labels`.")],
    allowed: Annotated[bool, typer.Option("--allowed/--refuse", help="Whether the policy allows the call "
                                          "(default: it does not: an incident).")] = False,
    note: Annotated[str | None, typer.Option(help="Why, kept with the record (not read by the converter).",
                                             show_default=False)] = None,
) -> None:
    """Mark a recorded call allowed or not: a labelled call for the set's next version."""
    record = _read(session, "SESSION")
    traj = record.get("traj") if isinstance(record, dict) else None
    if not isinstance(traj, list) or "task_id" not in record or "trial" not in record:
        _fail(f"{session}: not a recorded session ({{task_id, trial, traj: [messages]}})")
    found = [(index, c) for index, message in enumerate(traj) if isinstance(message, dict)
             for c in message.get("tool_calls") or [] if isinstance(c, dict) and c.get("id") == call]
    if not found:
        _fail(f"--call: {session} has no call {call!r}")
    index, made = found[0]
    function = made.get("function")
    tool = function.get("name") if isinstance(function, dict) else None
    existing = _read(labels, "--labels") if labels.exists() else []
    if not isinstance(existing, list):
        _fail(f"--labels {labels}: expected a list of label records")
    entry = {"task_id": record["task_id"], "trial": record["trial"], "message_index": index,
             "tool": tool, "allowed": allowed, "call": call, **({"note": note} if note else {})}
    labels.write_text(json.dumps([*existing, entry], indent=2) + "\n", encoding="utf-8")
    typer.echo(f"{labels}: [{len(existing)}] {call} ({entry['tool']}) of {record['task_id']}: "
               f"{'allowed' if allowed else 'refuse'}", err=True)


def register(app: typer.Typer) -> None:
    app.command("mcp")(mcp)
    app.command("label")(label)
