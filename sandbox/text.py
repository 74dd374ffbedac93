"""Untrusted text on its way to logs, JSON and HTTP."""

from __future__ import annotations

MESSAGE_CHARS = 500


def clean(text: str, limit: int = MESSAGE_CHARS) -> str:
    """No lone surrogates or undecodable bytes survive, and the length is bounded."""
    safe = text.encode("utf-8", "backslashreplace").decode("utf-8")
    return safe if len(safe) <= limit else safe[: limit - 3] + "..."
