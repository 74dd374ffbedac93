"""Reading JSON of an expected shape, with errors that name the file and the key where it is wrong."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from precond_client.openai_log import ConvertError

__all__ = ["ConvertError", "at", "expect", "key", "load_json"]


def load_json(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConvertError(f"{path}: cannot read: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ConvertError(f"{path}: not JSON: {exc}") from None
    return parse_json(text, str(path))


def parse_json(text: str, where: str) -> Any:
    """JSON from a user's file; every way it cannot be read (syntax, an integer of more than 4,300 digits, nesting
    deeper than the interpreter's stack) is a ConvertError naming `where`, never a traceback."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ConvertError(f"{where}: not JSON this tool reads: nested too deeply") from None
    except ValueError as exc:
        raise ConvertError(f"{where}: not JSON: {exc}") from None


def at(path: Path, where: str) -> str:
    return f"{path}: {where}" if where else str(path)


def expect(value: Any, kind: type | tuple[type, ...], path: Path, where: str) -> Any:
    if not isinstance(value, kind):
        names = " or ".join(k.__name__ for k in (kind if isinstance(kind, tuple) else (kind,)))
        raise ConvertError(f"{at(path, where or 'top level')}: expected {names}, found {type(value).__name__}")
    return value


def key(obj: dict[str, Any], name: str, kind: type | tuple[type, ...], path: Path, where: str) -> Any:
    if name not in obj:
        raise ConvertError(f"{at(path, where or 'top level')}: missing key {name!r}")
    return expect(obj[name], kind, path, f"{where}.{name}" if where else name)
