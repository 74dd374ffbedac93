"""`precond infer|next-action|check REQ.json`: the engine in-process, JSON in, JSON out; with `--server URL`
the same request goes to a running service through the Python client (`precond_client`) instead.

Errors go to stderr with a non-zero exit (2 for bad input or a refused API key, 3 for a resource limit, 4 when
the service cannot answer now: rate limited or unavailable after the client's retries), so scripts can tell a
bad request from a broken machine.
"""

from __future__ import annotations

import json
import re
import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer
from pydantic import BaseModel, ValidationError
from tqdm import tqdm

from precond.convert.shape import ConvertError, parse_json
from precond_client.schemas import (
    MAX_SOURCE_NAME_CHARS,
    CheckRequest,
    InferOptions,
    InferRequest,
    InferResponse,
    Listed,
    NextActionRequest,
    PriorSource,
    RuleEvidence,
)
from precond_client.schemas.errors import PrecondError, ResourceLimit

RequestFile = Annotated[Path, typer.Argument(help="Request body as JSON ('-' for standard input).")]
Server = Annotated[
    str | None,
    typer.Option(help="URL of a running service (e.g. http://127.0.0.1:8000): send the request there instead of "
                 "running the engine in-process.", envvar="PRECOND_SERVER", show_default=False),
]
ApiKey = Annotated[
    str | None,
    typer.Option(help="API key for --server (sent as `Authorization: Bearer`).", envvar="PRECOND_API_KEY",
                 show_default=False),
]


def _load(path: Path, model: type[BaseModel]) -> Any:
    try:
        text = sys.stdin.read() if str(path) == "-" else path.read_text(encoding="utf-8")
        return model.model_validate_json(text)
    except OSError as exc:
        _fail(f"cannot read {path}: {exc.strerror}", 2)
    except ValidationError as exc:
        _fail(f"invalid request in {path}:\n" + "\n".join(_problems(exc)), 2)
    except UnicodeDecodeError as exc:
        _fail(f"invalid request in {path}: not UTF-8: {exc.reason}", 2)


def _problems(error: ValidationError) -> list[str]:
    """`field: message` per problem, in the service's words (no pydantic prefix, type code or link)."""
    lines = []
    for problem in error.errors():
        field = ".".join(str(part) for part in problem["loc"]) or "body"
        message = re.sub(r"^(Value error|Assertion failed), ", "", problem["msg"])
        lines.append(f"  {field}: {message}")
    return lines


def _fail(message: str, code: int) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


class _Progress:
    """A tqdm bar on stderr that follows the engine's (phase, done, total) reports."""

    def __init__(self) -> None:
        self.bar = tqdm(total=1, file=sys.stderr, leave=False, disable=None)

    def __call__(self, phase: str, done: int, total: int) -> None:
        self.bar.set_description(phase)
        self.bar.total = max(total, 1)
        self.bar.n = done
        self.bar.refresh()

    def close(self) -> None:
        self.bar.close()


def _run(call: Callable[..., BaseModel], request: BaseModel, with_progress: bool = True,
         summary: bool = False) -> None:
    progress = _Progress() if with_progress else None
    try:
        response = call(request, progress) if progress else call(request)
    except ResourceLimit as exc:
        _fail(f"{exc.message}", 3)
    except PrecondError as exc:
        where = f" ({exc.field})" if exc.field else ""
        _fail(f"{exc.kind}{where}: {exc.message}", 2)
    finally:
        if progress:
            progress.close()
    _print(response, summary)


def _print(response: BaseModel, summary: bool = False) -> None:
    """The response as JSON on stdout (an inference with `--summary`: its summary instead); for an inference,
    the kept rules' exceptions on stderr, so that a user sees which demonstrated calls the rules refuse and can
    decide whether the log or the rule is wrong."""
    if summary and isinstance(response, InferResponse):
        typer.echo("\n".join(summary_lines(response)))
        return
    typer.echo(json.dumps(response.model_dump(mode="json"), indent=2))
    if isinstance(response, InferResponse):
        for line in [*left_out_lines(response), *exception_lines(response)]:
            typer.echo(line, err=True)


def left_out_lines(response: InferResponse) -> list[str]:
    """The warnings that name no action (a demonstration left out for its size), one line each."""
    return [f"WARNING {name}: {warning}" for name, warning in response.warnings.items()
            if name not in response.preconditions]


def _exceptions(evidence: RuleEvidence, indent: str) -> list[str]:
    lines = [f"{indent}demonstrations[{x.demonstration}], line {x.line}: {x.call}" for x in evidence.exceptions]
    unlisted = evidence.occurrences - evidence.holds - len(evidence.exceptions)
    return lines + ([f"{indent}... and {unlisted} more"] if unlisted > 0 else [])


def exception_lines(response: InferResponse) -> list[str]:
    lines = []
    for action, rules in response.evidence.items():
        for rule, evidence in rules.items():
            if evidence.holds == evidence.occurrences:
                continue
            lines.append(f"{action}: `{rule}` holds at {evidence.holds} of {evidence.occurrences} demonstrated calls "
                         f"(confidence {evidence.confidence:.2f}); exceptions:")
            lines += _exceptions(evidence, "  ")
    return lines


def summary_lines(response: InferResponse) -> list[str]:
    """What a person reads: per action its rules, how each was decided (its evidence and the kept candidate's
    reason), the demonstrated calls it refuses, and the action's warning (an empty or thin rule). A reason that
    several rules share (the ~60 words of why an assumed rule was kept) is said once, first, and named by its
    number at each rule."""
    decided = {(action, rule): _decided(response, action, rule)
               for action, rules in response.preconditions.items() for rule in rules}
    counts = Counter(reason for _, reason in decided.values() if reason)
    shared = {reason: n for n, reason in enumerate((r for r, c in counts.items() if c > 1), start=1)}
    lines = [f"[{n}] {reason}" for reason, n in shared.items()]
    for action, rules in response.preconditions.items():
        lines.append(f"{action}: " + (f"{len(rules)} rule(s), all must hold" if rules
                                      else "no rule: every call of it is allowed"))
        for rule in rules:
            lines.append(f"  {rule}")
            evidence = response.evidence.get(action, {}).get(rule)
            if evidence is not None:
                lines.append(f"    evidence: {evidence.verdict}, holds at {evidence.holds} of "
                             f"{evidence.occurrences} demonstrated calls (confidence {evidence.confidence:.2f})")
                lines += _exceptions(evidence, "    refuses ")
            label, reason = decided[(action, rule)]
            said = f"[{shared[reason]}]" if reason in shared else reason
            if said or label:
                lines.append(f"    decided: {label}{': ' if label and said else ''}{said}")
        if action in response.warnings:
            lines.append(f"  WARNING {response.warnings[action]}")
    lines += left_out_lines(response)
    kept = sum(len(r) for r in response.preconditions.values())
    lines.append(f"{kept} rule(s) for {len(response.preconditions)} action(s); {len(response.warnings)} warning(s)")
    return lines


def _decided(response: InferResponse, action: str, rule: str) -> tuple[str, str]:
    """How a kept rule was decided (its label, with where a transferred one came from) and the kept candidate's
    reason without what the evidence line already says."""
    evidence = response.evidence.get(action, {}).get(rule)
    reasons = {c.assertion: c.reason for c in response.candidates.get(action, []) if c.kept}
    label: str = evidence.decided if evidence is not None and evidence.decided else ""
    if evidence is not None and evidence.source:
        label = f"{evidence.decided} (from {evidence.source})"
    reason = str(reasons.get(rule) or "").split("; held at ")[0]  # its counts are the evidence line's
    if evidence is not None and evidence.decided and reason.startswith(f"{evidence.decided}:"):
        reason = reason[len(evidence.decided) + 1:].strip()
    return label, reason


def _remote(server: str, api_key: str | None, body: BaseModel, with_progress: bool = True,
            summary: bool = False) -> None:
    """The request through the client: a 202 is followed to the end, its progress drawn on stderr."""
    from precond_client import Client, JobStatus, PrecondError, RateLimited, Unavailable
    from precond_client import InvalidInput as ClientInvalidInput

    progress = _Progress() if with_progress else None

    def report(status: JobStatus) -> None:
        if progress is not None:
            progress(status.progress.phase, status.progress.done, status.progress.total)

    try:
        with Client(server, api_key=api_key) as client:
            if isinstance(body, InferRequest):
                response: BaseModel = client.infer_preconditions(body, progress=report)
            elif isinstance(body, NextActionRequest):
                response = client.next_action(body, progress=report)
            elif isinstance(body, CheckRequest):
                response = client.check_actions(body, progress=report)
            else:
                raise TypeError(f"no operation takes a {type(body).__name__}")
    except PrecondError as exc:
        where = f" ({exc.field})" if exc.field else ""
        kind = f"{exc.type}{where}: " if exc.type else ""
        code = 4 if isinstance(exc, RateLimited | Unavailable) else 2
        if isinstance(exc, ClientInvalidInput) and exc.type == "resource_limit":
            code = 3
        _fail(f"{kind}{exc.message}", code)
    finally:
        if progress:
            progress.close()
    _print(response, summary)


Summary = Annotated[bool, typer.Option("--summary", help="Print a summary to read (rules per action, how each "
                                       "was decided, the calls it refuses, warnings) instead of the JSON.")]
Candidates = Annotated[
    Listed | None,
    typer.Option(help="Which candidate reports the JSON lists (sets the request's options.candidates): kept (the "
                 "kept rules' only; the request's default), all (every dropped one too, with why), none.",
                 show_default=False),
]


PriorRules = Annotated[
    list[Path] | None,
    typer.Option("--prior-rules", help="Rules learned for another service, as priors (`options.prior_sources`, one "
                 "vote per file, named by it): a JSON object of action -> rules, or an inference's answer or a "
                 "stored set (its `preconditions`); repeatable.", show_default=False),
]


def infer(request: RequestFile, server: Server = None, api_key: ApiKey = None, summary: Summary = False,
          candidates: Candidates = None, prior_rules: PriorRules = None) -> None:
    """Infer verified preconditions for the spec's actions from the demonstrations."""
    body = _load(request, InferRequest)
    if prior_rules:
        sources = [*body.options.prior_sources, *(_prior_source(path) for path in prior_rules)]
        body = _with_options(body, {"prior_sources": [s.model_dump() for s in sources]})
    listed = candidates or ("kept" if summary and body.options.candidates == "none" else None)
    if listed:
        body = body.model_copy(update={"options": body.options.model_copy(update={"candidates": listed})})
    if server:
        return _remote(server, api_key, body, summary=summary)
    from precond.engine.factory import build_engine

    engine = build_engine(with_model="model" in body.options.generators)
    _run(engine.infer, body, summary=summary)


def _prior_source(path: Path) -> PriorSource:
    """A file of rules as one prior source: `{action: [rules]}`, or anything with `preconditions`."""
    try:
        loaded = parse_json(path.read_text(encoding="utf-8"), f"--prior-rules {path}")
        rules = loaded.get("preconditions", loaded) if isinstance(loaded, dict) else loaded
        return PriorSource.model_validate({"source": path.name[:MAX_SOURCE_NAME_CHARS], "rules": rules})
    except OSError as exc:
        _fail(f"cannot read {path}: {exc.strerror}", 2)
    except ConvertError as exc:
        _fail(str(exc), 2)
    except ValidationError as exc:
        _fail(f"--prior-rules {path}: not rules per action:\n" + "\n".join(_problems(exc)), 2)
    raise AssertionError("unreachable")


def _with_options(body: InferRequest, update: dict[str, Any]) -> InferRequest:
    """The request with options changed, validated again (the bound on prior rules counts them all)."""
    try:
        return body.model_copy(update={"options": InferOptions.model_validate({**body.options.model_dump(), **update})})
    except ValidationError as exc:
        _fail("invalid options:\n" + "\n".join(_problems(exc)), 2)
    raise AssertionError("unreachable")


def next_action(
    request: RequestFile,
    adapter: Annotated[Path | None, typer.Option(help="A trained policy (`precond train-policy --out DIR`): the "
                                                 "model predicts with it beside its weights, unmerged, as the "
                                                 "service serves it (BC).", show_default=False)] = None,
    server: Server = None,
    api_key: ApiKey = None,
) -> None:
    """Predict the next action(s) after the history, verified against the preconditions (Algorithm 1)."""
    body = _load(request, NextActionRequest)
    if server:
        if adapter is not None:
            _fail("--adapter is a directory here, in-process: with --server name one of your stored policies in "
                  "the request (options.policy: \"adapter:<id>\", made by POST /policies)", 2)
        return _remote(server, api_key, body)
    if body.options.policy is not None:
        _fail(f"options.policy: {body.options.policy} is a policy stored in the service: send the request with "
              "--server, or give the adapter's directory with --adapter and leave options.policy out", 2)
    from precond.engine.factory import build_engine

    engine = build_engine()
    _run((engine if adapter is None else engine.with_policy(adapter, None)).next_action, body)


def train_policy(
    request: RequestFile,
    out: Annotated[Path, typer.Option("--out", help="Directory the adapter is written to (whole or not at all).")],
) -> None:
    """Fine-tune the code model on the demonstrations' action lines (LoRA behaviour cloning, `MODEL_*`
    settings; MODEL_THREADS=2 on two cores); prints what it trained and cost."""
    from precond_client.schemas.training import TrainPolicyRequest

    body = _load(request, TrainPolicyRequest)
    from precond.engine.acting.training import train_policy as train
    from precond.engine.models.weights import load_weights
    from precond.engine.settings import ModelSettings
    from precond.engine.spec import parse_spec

    def run(req: TrainPolicyRequest, progress: Callable[[str, int, int], None]) -> BaseModel:
        return train(lambda: load_weights(ModelSettings()), parse_spec(req.spec), req, out, progress, lambda: False)

    _run(run, body)


def _openai_check(messages: Path, spec: Path | None, rules: Path | None, precondition_set: str | None,
                  calls: list[str]) -> CheckRequest:
    """A check request from an agent's OpenAI messages (a list, or a tau-bench `{"traj": [...]}` record), the
    rules (a file of `{action: [rules]}` or an infer response, with the spec; or a stored set) and tool calls."""
    try:
        history = parse_json(messages.read_text(encoding="utf-8"), str(messages))
        if isinstance(history, dict) and "traj" in history:
            history = history["traj"]
        fields: dict[str, Any] = {"history": history,
                                  "calls": [parse_json(c, f"--call {n + 1}") for n, c in enumerate(calls)]}
        if precondition_set is not None:
            fields["precondition_set"] = precondition_set
        if spec is not None:
            fields["spec"] = spec.read_text(encoding="utf-8")
        if rules is not None:
            loaded = parse_json(rules.read_text(encoding="utf-8"), str(rules))
            fields["preconditions"] = loaded.get("preconditions", loaded) if isinstance(loaded, dict) else loaded
            fields["decided"] = _decided_of(loaded)
        return CheckRequest.model_validate(fields)
    except OSError as exc:
        _fail(f"cannot read {exc.filename}: {exc.strerror}", 2)
    except ConvertError as exc:
        _fail(str(exc), 2)
    except ValidationError as exc:
        _fail(f"invalid check:\n{exc}", 2)
    raise AssertionError("unreachable")


def _decided_of(loaded: Any) -> Any:
    """How each rule was decided, from an infer response's `evidence` (so that each verdict's `rule_status` says
    it); a plain `{action: [rules]}` file says nothing of it (its rules are 'given')."""
    evidence = loaded.get("evidence") if isinstance(loaded, dict) and "preconditions" in loaded else None
    if not isinstance(evidence, dict):
        return {}
    return {action: {rule: found["decided"] for rule, found in rules.items()
                     if isinstance(found, dict) and isinstance(found.get("decided"), str)}
            for action, rules in evidence.items() if isinstance(rules, dict)}


def check(
    request: Annotated[Path | None, typer.Argument(help="Request body as JSON ('-' for standard input); not with "
                                                   "--openai.", show_default=False)] = None,
    openai: Annotated[Path | None, typer.Option(help="An agent's OpenAI chat messages (a list, or a tau-bench "
                                                "record) as the history; with --call, --spec and --rules (or "
                                                "--precondition-set).", show_default=False)] = None,
    call: Annotated[list[str] | None, typer.Option(help="With --openai: a proposed tool call as JSON, "
                                                   "{\"name\": ..., \"arguments\": {...}}; repeatable.",
                                                   show_default=False)] = None,
    spec: Annotated[Path | None, typer.Option(help="With --openai: the spec (from `precond convert openai`).",
                                              show_default=False)] = None,
    rules: Annotated[Path | None, typer.Option(help="With --openai: the rules, {action: [rules]} or an infer "
                                               "response.", show_default=False)] = None,
    precondition_set: Annotated[str | None, typer.Option(help="With --openai and --server: a stored set instead "
                                                         "of --spec and --rules.", show_default=False)] = None,
    batch: Annotated[Path | None, typer.Option(help="Many checks in one command: a JSON list of {\"history\": "
                                               "OpenAI messages (or a program), \"call\": {\"name\", "
                                               "\"arguments\"} (or a program line)}, with --spec and --rules; one "
                                               "verdict a line (JSON).", show_default=False)] = None,
    server: Server = None,
    api_key: ApiKey = None,
) -> None:
    """Say for each proposed call whether the preconditions allow it after the history (no model)."""
    if batch is not None:
        return _batch(batch, spec, rules)
    if (openai is None) == (request is None):
        _fail("give a request file, or --openai MESSAGES.json with --call (not both)", 2)
    if openai is not None and not call:
        _fail("--openai needs at least one --call '{\"name\": ..., \"arguments\": {...}}'", 2)
    if openai is not None:
        body = _openai_check(openai, spec, rules, precondition_set, call or [])
    elif request is not None:
        body = _load(request, CheckRequest)
    if server:
        return _remote(server, api_key, body, with_progress=False)
    from precond.engine.factory import build_engine

    _run(build_engine(with_model=False).check, body, with_progress=False)


def _batch(pairs_file: Path, spec: Path | None, rules: Path | None) -> None:
    """Every (history, call) pair of the file judged in this process, by one engine: the start-up is paid once.
    A pair the service would refuse exits 2 naming it (`PAIRS.json: [3]: history[2].content: ...`)."""
    if spec is None or rules is None:
        _fail("--batch needs --spec and --rules", 2)
        return
    try:
        pairs = parse_json(pairs_file.read_text(encoding="utf-8"), str(pairs_file))
        spec_text = spec.read_text(encoding="utf-8")
        loaded = parse_json(rules.read_text(encoding="utf-8"), str(rules))
    except OSError as exc:
        _fail(f"cannot read {exc.filename}: {exc.strerror}", 2)
    except ConvertError as exc:
        _fail(str(exc), 2)
    if not isinstance(pairs, list) or not all(isinstance(p, dict) and {"history", "call"} <= set(p) for p in pairs):
        _fail(f"{pairs_file}: expected a list of {{\"history\": ..., \"call\": ...}}", 2)
    preconditions = loaded.get("preconditions", loaded) if isinstance(loaded, dict) else loaded
    decided = _decided_of(loaded)
    from precond.engine.factory import build_engine

    engine = build_engine(with_model=False)
    for index, pair in enumerate(pairs):
        where = f"{pairs_file}: [{index}]"
        try:
            body = CheckRequest.model_validate({"spec": spec_text, "preconditions": preconditions,
                                                "decided": decided, "history": pair["history"],
                                                "calls": [pair["call"]]})
            verdict = engine.check(body).results[0]
        except ValidationError as exc:
            _fail(f"{where}:\n" + "\n".join(_problems(exc)), 2)
        except PrecondError as exc:
            _fail(f"{where}: {exc.kind}{f' ({exc.field})' if exc.field else ''}: {exc.message}", 2)
        typer.echo(json.dumps(verdict.model_dump(mode="json")))


def register(app: typer.Typer) -> None:
    app.command("infer")(infer)
    app.command("next-action")(next_action)
    app.command("check")(check)
    app.command("train-policy")(train_policy)
