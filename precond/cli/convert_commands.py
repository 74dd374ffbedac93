"""`precond convert sgd|events|openai`: users' own dialog data → spec, demonstration programs and an infer request
(the rules: docs/converting.md). Input of the wrong shape exits 2 naming the file and the key."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Annotated, Any

import typer
from pydantic import ValidationError

from precond.convert import events as events_converter
from precond.convert import labels as labels_reader
from precond.convert import openai as openai_converter
from precond.convert import sgd as sgd_converter
from precond.convert.shape import ConvertError, load_json
from precond.programs import checks
from precond_client.openai_log import MAX_SEEN
from precond_client.schemas import MAX_COUNTEREXAMPLE_RUNS, MAX_LABELLED_CALLS, InferRequest

app = typer.Typer(help="Convert dialog data (SGD files, JSON event logs) to a spec, programs and a request.",
                  no_args_is_help=True)


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


def _request(spec: str, demonstrations: list[str], actions: list[str] | None = None,
             counterexamples: list[dict[str, Any]] | None = None) -> str:
    body = InferRequest.model_validate({"spec": spec, "demonstrations": demonstrations, "actions": actions,
                                        "counterexamples": counterexamples or []})
    return json.dumps(body.model_dump(mode="json", exclude_defaults=True), indent=2) + "\n"


@app.command("sgd")
def sgd(
    schema: Annotated[Path, typer.Argument(help="SGD's schema.json (the services).")],
    dialogues: Annotated[list[Path], typer.Argument(help="SGD's dialogues_*.json files.")],
    out: Annotated[Path, typer.Option(help="Directory for spec.py, demos/<dialogue_id>.py and request.json.")],
    service: Annotated[str | None, typer.Option(help="The service (e.g. Buses_1); needed when the schema "
                                                     "lists several.", show_default=False)] = None,
    demos: Annotated[int, typer.Option(min=1, max=200, help="How many dialogues go into request.json.")] = 10,
) -> None:
    """SGD dialogues of one service → its spec, one demonstration program per dialogue, an infer request."""
    try:
        converted = sgd_converter.convert(schema, dialogues, service)
    except ConvertError as exc:
        _fail(str(exc))
    (out / "demos").mkdir(parents=True, exist_ok=True)
    (out / "spec.py").write_text(converted.spec, encoding="utf-8")
    for dialogue_id, program in converted.demonstrations.items():
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", dialogue_id)
        (out / "demos" / f"{name}.py").write_text(program, encoding="utf-8")
    chosen = list(converted.demonstrations.values())[:demos]
    (out / "request.json").write_text(_request(converted.spec, chosen), encoding="utf-8")
    typer.echo(f"{converted.service.name}: {len(converted.demonstrations)} dialogues → {out}/demos/, "
               f"{len(chosen)} in {out}/request.json; {converted.skipped} skipped (other services)", err=True)


@app.command("events")
def events(
    events_file: Annotated[Path, typer.Argument(metavar="EVENTS.json", help="A list of events (one trajectory) "
                                                "or a list of such lists; an event: {actor, act, args}.")],
    spec: Annotated[Path, typer.Option(help="The spec program (Python) the events are calls of.")],
    setup: Annotated[Path | None, typer.Option(help="Statements making the objects (default: one per spec class, "
                                               "`system = SYSTEM(user)`).", show_default=False)] = None,
    request: Annotated[Path | None, typer.Option(help="Write an infer request (spec + programs) here instead of "
                                                 "printing the programs.", show_default=False)] = None,
) -> None:
    """JSON events → programs over your spec (printed, or as an infer request with --request)."""
    try:
        spec_text, programs = events_converter.convert(events_file, spec, setup)
    except ConvertError as exc:
        _fail(str(exc))
    if request is not None:
        request.write_text(_request(spec_text, programs), encoding="utf-8")
        return
    for index, program in enumerate(programs):
        if len(programs) > 1:
            typer.echo(f"# trajectory {index}")
        typer.echo(program)


def _tool_names(value: str | None) -> set[str] | None:
    return None if value is None else {w.strip() for w in value.split(",") if w.strip()}


@app.command("openai")
def openai(
    trajectories: Annotated[Path, typer.Argument(metavar="TRAJECTORIES.json", help="OpenAI chat messages: one "
                                                 "trajectory (a list of messages), a list of them, or tau-bench's "
                                                 "{\"traj\": [...]} records; or a folder of files of one "
                                                 "trajectory each (`precond mcp`'s sessions/).")],
    tools: Annotated[Path, typer.Option(help="The tools' OpenAI function schemas (a JSON list).")],
    out: Annotated[Path, typer.Option(help="Directory for spec.py, demos/<n>.py and request.json.")],
    writes: Annotated[str | None, typer.Option("--writes", "--state-changing", help="Comma-separated tools that "
                                               "change state: their results go to `self.changes`, a read's to "
                                               "`self.results` (default: tools named book_, cancel_, update_, "
                                               "send_, ...).", show_default=False)] = None,
    guard: Annotated[str | None, typer.Option(help="Comma-separated tools to infer rules for, request.json's "
                                              "actions (default: every tool, reads included).",
                                              show_default=False)] = None,
    min_reward: Annotated[float | None, typer.Option(help="Only records with at least this reward go into "
                                                     "request.json (tau-bench: 1 = the run succeeded).",
                                                     show_default=False)] = None,
    demos: Annotated[int, typer.Option(min=1, max=200, help="How many trajectories go into request.json.")] = 200,
    labels: Annotated[Path | None, typer.Option(help="Labelled calls ({run, message_index, tool, allowed} or "
                                                "{task_id, trial, message_index, tool, allowed} records): "
                                                "request.json's counterexamples, with the labels the calls carry.",
                                                show_default=False)] = None,
) -> None:
    """Tool-calling agent logs → a spec from the tool schemas, one program per trajectory, an infer request."""
    if guard is not None and not _tool_names(guard):
        _fail("--guard: names no tool (leave it out to guard every tool)")
    files: list[Path] = []
    try:
        data, files = _trajectories(trajectories)
        converted = openai_converter.convert(data, load_json(tools), str(trajectories), str(tools),
                                             _tool_names(writes), _tool_names(guard))
        read = labels_reader.on_calls(converted) + ([] if labels is None else labels_reader.read_labels(
            load_json(labels), str(labels), {t.name for t in converted.tools},
            [t.name for t in converted.trajectories]))
    except ConvertError as exc:
        _fail(_in_file(str(exc), str(trajectories), files))
    (out / "demos").mkdir(parents=True, exist_ok=True)
    (out / "spec.py").write_text(converted.spec, encoding="utf-8")
    for trajectory in converted.trajectories:
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", trajectory.name)
        (out / "demos" / f"{name}.py").write_text(trajectory.program, encoding="utf-8")
    kept = [t for t in converted.trajectories
            if min_reward is None or (t.reward is not None and t.reward >= min_reward)][:demos]
    try:
        counted = labels_reader.counted(converted, read, kept)
        body = _request(converted.spec, [t.program for t in kept],
                        [f"AGENT.{w}" for w in sorted(converted.guarded)] or None, counted.runs)
    except ConvertError as exc:
        _fail(str(exc))
    except ValidationError as exc:
        _fail(f"{out / 'request.json'}: {_first_error(exc)}")
    (out / "request.json").write_text(body, encoding="utf-8")
    typer.echo(_openai_summary(converted, len(kept), out, counted if read else None), err=True)


def _first_error(exc: ValidationError) -> str:
    """The request's first problem, naming its field (`counterexamples`, `demonstrations[3]`)."""
    error = exc.errors()[0]
    field = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in error["loc"]).lstrip(".")
    return f"{field}: {error['msg']}"


def _openai_summary(converted: openai_converter.Converted, demos: int, out: Path,
                    counted: labels_reader.Counted | None) -> str:
    calls = [c["verdict"] for run in counted.runs for c in run["calls"]] if counted else []
    left = (f"; {counted.runs_left_out} labelled runs ({counted.calls_left_out} calls) left out: a request takes "
            f"at most {MAX_COUNTEREXAMPLE_RUNS} runs of at most {MAX_LABELLED_CALLS} labelled calls, those that carry "
            "a refusal first" if counted and counted.calls_left_out else "")
    return (f"{len(converted.trajectories)} trajectories → {out}/demos/, {demos} in {out}/request.json (actions: "
            f"{', '.join(sorted(converted.guarded))}; state-changing: {', '.join(sorted(converted.writes)) or 'none'}"
            f"); {converted.without_writes} without a state-changing call"
            + (f"; labelled calls: {calls.count('refuse')} to refuse, {calls.count('allow')} to allow, in "
               f"{len(counted.runs)} runs" if counted else "") + left
            + (f"; {counted.skipped} labels of tools that are not actions left out" if counted and counted.skipped
               else "")
            + (f"; in {past} trajectories a read tool listed more than {MAX_SEEN} records: `self.seen` keeps "
               "the last of them" if (past := converted.past_seen) else ""))


def _trajectories(path: Path) -> tuple[Any, list[Path]]:
    """A file's trajectories; or a folder's `*.json` files in name order, one trajectory each (a list of messages
    or a `{"traj": [...]}` record: what `precond mcp` records per session), and the files."""
    if not path.is_dir():
        return load_json(path), []
    files = sorted(path.glob("*.json"))
    if not files:
        raise ConvertError(f"{path}: no *.json files in the folder")
    return [load_json(file) for file in files], files


def _in_file(message: str, source: str, files: list[Path]) -> str:
    """An error at `FOLDER: [3]...` said at the file it is in (the folder's fourth)."""
    found = re.match(re.escape(source) + r": \[(\d+)\]", message)
    if not files or found is None or int(found[1]) >= len(files):
        return message
    return f"{files[int(found[1])]}: {message[found.end():].lstrip('.: ')}"


@app.command("programs")
def programs(
    spec: Annotated[Path, typer.Option(help="The spec program (Python).")],
    demonstrations: Annotated[list[Path], typer.Argument(metavar="DEMO.py...", help="Demonstration programs over "
                                                         "the spec, one per file (e.g. demos/*.py), in this order.")],
    request: Annotated[Path | None, typer.Option(help="Write the infer request here instead of printing it.",
                                                 show_default=False)] = None,
) -> None:
    """spec.py + demos/*.py → an infer request, each program parsed first (an error names its file and line)."""
    try:
        spec_text = spec.read_text(encoding="utf-8")
        texts = [path.read_text(encoding="utf-8") for path in demonstrations]
    except (OSError, UnicodeDecodeError) as exc:
        _fail(f"cannot read {getattr(exc, 'filename', None) or 'a file'}: {exc}")
    names = {f"demonstrations[{i}]": str(path) for i, path in enumerate(demonstrations)}
    try:
        checks.check_infer(spec_text, texts, None)
    except checks.ProgramProblem as exc:
        where = names.get(exc.problem.field, str(spec) if exc.problem.field == "spec" else "")
        _fail(f"{where}: {exc.problem.message}" if where else exc.problem.message)
    try:
        body = _request(spec_text, texts)
    except ValidationError as exc:
        _fail(f"not a valid request: {exc}")
    if request is None:
        typer.echo(body, nl=False)
    else:
        request.write_text(body, encoding="utf-8")
        typer.echo(f"{len(texts)} demonstrations → {request}", err=True)


def register(root: typer.Typer) -> None:
    root.add_typer(app, name="convert")
