"""`precond infer|next-action|check REQ.json`: the engine in-process, JSON in, JSON out.

Errors go to stderr with a non-zero exit (2 for bad input, 3 for a resource limit), so scripts can tell a
bad request from a broken machine.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer
from pydantic import BaseModel, ValidationError
from tqdm import tqdm

from schemas.api import CheckRequest, InferRequest, NextActionRequest
from schemas.errors import PrecondError, ResourceLimit

RequestFile = Annotated[Path, typer.Argument(help="Request body as JSON ('-' for standard input).")]


def _load(path: Path, model: type[BaseModel]) -> Any:
    try:
        text = sys.stdin.read() if str(path) == "-" else path.read_text(encoding="utf-8")
        return model.model_validate_json(text)
    except OSError as exc:
        _fail(f"cannot read {path}: {exc.strerror}", 2)
    except (ValidationError, UnicodeDecodeError) as exc:
        _fail(f"invalid request in {path}:\n{exc}", 2)


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


def _run(call: Callable[..., BaseModel], request: BaseModel, with_progress: bool = True) -> None:
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
    typer.echo(json.dumps(response.model_dump(mode="json"), indent=2))


def infer(request: RequestFile) -> None:
    """Infer verified preconditions for the spec's actions from the demonstrations."""
    from engine.factory import build_engine

    body = _load(request, InferRequest)
    engine = build_engine(with_model="model" in body.options.generators)
    _run(engine.infer, body)


def next_action(request: RequestFile) -> None:
    """Predict the next action(s) after the history, verified against the preconditions (Algorithm 1)."""
    from engine.factory import build_engine

    body = _load(request, NextActionRequest)
    _run(build_engine().next_action, body)


def check(request: RequestFile) -> None:
    """Say for each proposed call whether the preconditions allow it after the history (no model)."""
    from engine.factory import build_engine

    body = _load(request, CheckRequest)
    _run(build_engine(with_model=False).check, body, with_progress=False)


def register(app: typer.Typer) -> None:
    app.command("infer")(infer)
    app.command("next-action")(next_action)
    app.command("check")(check)
