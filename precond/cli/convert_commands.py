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
from precond_client.schemas.api import InferRequest

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


@app.command("openai")
def openai(
    trajectories: Annotated[Path, typer.Argument(metavar="TRAJECTORIES.json", help="OpenAI chat messages: one "
                                                 "trajectory (a list of messages), a list of them, or tau-bench's "
                                                 "{\"traj\": [...]} records; or a folder of files of one "
                                                 "trajectory each (`precond mcp`'s sessions/).")],
    tools: Annotated[Path, typer.Option(help="The tools' OpenAI function schemas (a JSON list).")],
    out: Annotated[Path, typer.Option(help="Directory for spec.py, demos/<n>.py and request.json.")],
    writes: Annotated[str | None, typer.Option(help="Comma-separated state-changing tools, the actions request.json "
                                               "asks rules for (default: tools named book_, cancel_, update_, "
                                               "send_, ...).", show_default=False)] = None,
    min_reward: Annotated[float | None, typer.Option(help="Only records with at least this reward go into "
                                                     "request.json (tau-bench: 1 = the run succeeded).",
                                                     show_default=False)] = None,
    demos: Annotated[int, typer.Option(min=1, max=200, help="How many trajectories go into request.json.")] = 200,
    labels: Annotated[Path | None, typer.Option(help="Labelled calls ({task_id, trial, message_index, tool, allowed} "
                                                "records): request.json's counterexamples.",
                                                show_default=False)] = None,
) -> None:
    """Tool-calling agent logs → a spec from the tool schemas, one program per trajectory, an infer request."""
    chosen = None if writes is None else {w.strip() for w in writes.split(",") if w.strip()}
    files: list[Path] = []
    try:
        data, files = _trajectories(trajectories)
        converted = openai_converter.convert(data, load_json(tools), str(trajectories), str(tools), chosen)
        read = [] if labels is None else labels_reader.read_labels(load_json(labels), str(labels),
                                                                    {t.name for t in converted.tools})
    except ConvertError as exc:
        _fail(_in_file(str(exc), str(trajectories), files))
    (out / "demos").mkdir(parents=True, exist_ok=True)
    (out / "spec.py").write_text(converted.spec, encoding="utf-8")
    for trajectory in converted.trajectories:
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", trajectory.name)
        (out / "demos" / f"{name}.py").write_text(trajectory.program, encoding="utf-8")
    kept = [t for t in converted.trajectories
            if min_reward is None or (t.reward is not None and t.reward >= min_reward)]
    chosen_programs = [t.program for t in kept][:demos]
    actions = [f"AGENT.{w}" for w in sorted(converted.writes)] or None
    try:
        runs = labels_reader.counterexamples(converted, read, kept[:demos])
    except ConvertError as exc:
        _fail(str(exc))
    (out / "request.json").write_text(_request(converted.spec, chosen_programs, actions, runs), encoding="utf-8")
    counted = [c["verdict"] for run in runs for c in run["calls"]]
    typer.echo(f"{len(converted.trajectories)} trajectories → {out}/demos/, {len(chosen_programs)} in "
               f"{out}/request.json (actions: {', '.join(sorted(converted.writes)) or 'all'}); "
               f"{converted.without_writes} without a state-changing call"
               + (f"; labelled calls: {counted.count('refuse')} to refuse, {counted.count('allow')} to allow, "
                  f"in {len(runs)} runs" if labels is not None else "")
               + (f"; {left} labels of tools that are not actions left out"
                  if (left := labels_reader.skipped(converted, read)) else "")
               + (f"; in {past} trajectories a read tool listed more than {MAX_SEEN} records: `self.seen` keeps "
                  "the last of them" if (past := converted.past_seen) else ""), err=True)


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
