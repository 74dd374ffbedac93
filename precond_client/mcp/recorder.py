"""What the proxy writes: each MCP session's tool calls and results as OpenAI chat messages, in one record that
`precond convert openai` reads as it is (`{"task_id": SESSION, "trial": 0, "traj": [messages]}`), and one JSON
line per call in `calls.jsonl` (the session, the call, the verdict, what was done with it).

A session's record is valid JSON after every call: a message is written over the record's closing brackets and
the brackets again after it, so a proxy that is stopped (or killed) between calls leaves every call it answered
recorded. A record is bounded (`max_bytes`): a call whose message would pass the bound is refused before it
reaches the upstream (`LogFull`), and a result too long for the room left is recorded cut, said in its text.
Each record's file stays open while its session is held in memory (one `pwrite` a message, no open or close).

`calls.jsonl` is bounded too (`max_bytes`, `--max-calls-bytes`): each call takes `LINE_ROOM` bytes of room
before it is made, and a call with no room is refused (`LogFull`, naming the file and the bound) rather than
made unlogged; a file moved away at its bound (log rotation) is started again. Each line is written whole and
flushed as the call is answered: a proxy stopped or killed loses no answered call's line.
"""

from __future__ import annotations

import json
import os
import re
import time
import uuid
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

CLOSE = b"\n]}\n"
RESULT_ROOM = 4096
"""Bytes kept free, when a call is recorded, for its result (a longer result is cut to the room left)."""
CUT = " ... [cut: the session's log reached its bound]"


class LogFull(Exception):
    """A call refused because its session's record reached its bound: the message names the bound."""


def session_name() -> str:
    """Sortable by start and unique: `20261207T164500-1a2b3c4d`."""
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + uuid.uuid4().hex[:8]


@dataclass
class Recording:
    """One session's record, open for appending (`close` when the session is forgotten)."""

    name: str
    path: Path
    max_bytes: int
    descriptor: int
    size: int = 0
    messages: int = 0
    calls: int = 0

    @classmethod
    def start(cls, folder: Path, name: str, max_bytes: int) -> Recording:
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:100]
        path = folder / f"{safe}.json"
        head = json.dumps({"task_id": name, "trial": 0}).encode()[:-1] + b', "traj": ['
        # O_EXCL: a name never reused, a record never overwritten
        descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
        os.pwrite(descriptor, head + CLOSE, 0)
        return cls(name, path, max_bytes, descriptor, len(head) + len(CLOSE))

    def call(self, tool: str, arguments: dict[str, Any]) -> tuple[str, dict[str, Any]]:
        """The assistant message of a call, with its id (`call_3`), once the record has room for it and a
        result; `LogFull` otherwise."""
        self.calls += 1
        call_id = f"call_{self.calls}"
        message = {"role": "assistant", "content": None, "tool_calls": [
            {"id": call_id, "type": "function", "function": {"name": tool, "arguments": json.dumps(arguments)}}]}
        encoded = _encoded(message)
        if self.size + len(encoded) + RESULT_ROOM > self.max_bytes:
            self.calls -= 1
            raise LogFull(f"this session's log reached its bound ({self.max_bytes} bytes, --max-log-bytes): "
                          "the call was not made; start a new session")
        self._append(encoded)
        return call_id, message

    def result(self, call_id: str, tool: str, content: str) -> dict[str, Any]:
        """The tool message of a result (cut to the room the bound leaves), recorded."""
        message = {"role": "tool", "tool_call_id": call_id, "name": tool, "content": content}
        encoded = _encoded(message)
        keep = len(content)
        while len(encoded) > self.max_bytes - self.size and keep > 0:  # bytes, not characters: shrink until it fits
            keep = max(0, keep - (len(encoded) - (self.max_bytes - self.size)) - 2 * len(CUT))
            message["content"] = content[:keep] + CUT
            encoded = _encoded(message)
        self._append(encoded)
        return message

    def _append(self, encoded: bytes) -> None:
        separator = b"\n" if self.messages == 0 else b",\n"
        os.pwrite(self.descriptor, separator + encoded + CLOSE, self.size - len(CLOSE))
        self.size += len(separator) + len(encoded)
        self.messages += 1

    def close(self) -> None:
        with suppress(OSError):
            os.close(self.descriptor)


def _encoded(message: dict[str, Any]) -> bytes:
    return json.dumps(message, ensure_ascii=False).encode("utf-8", "backslashreplace")


LINE_ROOM = 16 * 1024
"""Bytes of `calls.jsonl` a call holds while it is served; a longer line has its verdict's details cut."""


class CallLog:
    """`calls.jsonl`: one line per call, within `max_bytes`; `reserve` before a call, `write` once answered."""

    def __init__(self, folder: Path, max_bytes: int) -> None:
        self.path = folder / "calls.jsonl"
        self.max_bytes = max_bytes
        self.reserved = 0
        self.handle = self._open()

    def _open(self) -> Any:
        handle = open(self.path, "ab", opener=_private)  # noqa: SIM115 (closed by close)
        self.size = handle.tell()
        return handle

    def reserve(self) -> None:
        """Room for one call's line, or `LogFull` naming the bound (once the full file was moved away, a new one
        is started)."""
        if self.size + self.reserved + LINE_ROOM > self.max_bytes and self._moved():
            self.handle.close()
            self.handle = self._open()
        if self.size + self.reserved + LINE_ROOM > self.max_bytes:
            raise LogFull(f"{self.path.name} reached its bound ({self.max_bytes} bytes, --max-calls-bytes): the call "
                          "was not made; move the file away (it is started again) or restart with a higher bound")
        self.reserved += LINE_ROOM

    def _moved(self) -> bool:
        try:
            now = os.stat(self.path)
        except FileNotFoundError:
            return True
        held = os.fstat(self.handle.fileno())
        return (now.st_dev, now.st_ino) != (held.st_dev, held.st_ino)

    def release(self) -> None:
        """The room `reserve` held, given back once the call's line is written (or it never will be)."""
        self.reserved -= LINE_ROOM

    def write(self, entry: dict[str, Any]) -> None:
        """The line of a call `reserve` made room for, written whole and flushed."""
        line = _line(entry)
        if len(line) > LINE_ROOM:  # a verdict with many long rules: its details cut, said
            kept = {key: str(entry.get(key, ""))[:200] for key in ("session", "call", "tool", "mode", "outcome")}
            verdict = entry.get("verdict") or {}
            line = _line({**kept, "ms": entry.get("ms"), "upstream_ms": entry.get("upstream_ms"),
                          "verdict": {"allowed": verdict.get("allowed"),
                                      "cut": f"the line passed {LINE_ROOM} bytes: the verdict's details left out"}})
        self.handle.write(line)
        self.handle.flush()
        self.size += len(line)

    def close(self) -> None:
        self.handle.close()


def _line(entry: dict[str, Any]) -> bytes:
    return (json.dumps(entry, ensure_ascii=False) + "\n").encode("utf-8", "backslashreplace")


def _private(path: str, flags: int) -> int:
    return os.open(path, flags, 0o600)


def prepare(folder: Path) -> Path:
    """The log folder and its `sessions/`, made private to the user (tool results can be anyone's data)."""
    sessions = folder / "sessions"
    sessions.mkdir(parents=True, exist_ok=True)
    for made in (folder, sessions):
        os.chmod(made, 0o700)
    return sessions
