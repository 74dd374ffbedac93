"""Lua scripts run by their digest (EVALSHA): the hot path's scripts are 1-2 KB each, and EVAL sends the text
and has Redis hash it at every call. A Redis that does not know the script yet (a restart, a flush, a new
server) answers NOSCRIPT, and the text is sent once more with EVAL, which also keeps it for the next call."""

from __future__ import annotations

import hashlib
from typing import Any

from redis.asyncio import Redis
from redis.exceptions import NoScriptError


class LuaScript:
    def __init__(self, text: str) -> None:
        self.text = text
        self.sha = hashlib.sha1(text.encode()).hexdigest()

    async def __call__(self, redis: Redis[bytes], keys: list[Any], args: list[Any]) -> Any:
        try:
            return await redis.evalsha(self.sha, len(keys), *keys, *args)  # type: ignore[no-untyped-call]
        except NoScriptError:
            return await redis.eval(self.text, len(keys), *keys, *args)  # type: ignore[no-untyped-call]
