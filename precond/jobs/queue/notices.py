"""Completion notices: how a worker tells the gateway processes waiting on a job that its end is stored.

Each gateway process subscribes to a channel of its own (`notice_channel`), and a request that waits on a job
adds that channel to the job's waiters (`waiters_key`) in the script that submits it. The script that stores a
job's end publishes on each waiter's channel and forgets them (`NOTIFY_FUNCTION`), so a finished job wakes only
the processes that wait on it, not every gateway process (a pattern subscription woke them all, on two cores).

A notice carries the job's end as stored, read in the same step that stored it (`record`): the id, the
progress and arq's result, so a waiter answers without reading them back. A notice of an end that is not final
(a run handed back to the queue) or larger than `RECORD_MAX_BYTES` carries the id alone, and the waiter reads
the job's state. Notices are still never the only way: a lost one costs a waiter its fallback read.
"""

from __future__ import annotations

from typing import Final

from precond.jobs.queue.keys import PREFIX

WAITERS_PREFIX: Final = f"{PREFIX}:waiters:"
NOTICE_PREFIX: Final = f"{PREFIX}:notice:"
RECORD_MAX_BYTES: Final = 64 * 1024
"""The largest result a notice carries; a larger one is read back by the waiter."""
WAITERS_TTL_S: Final = 24 * 3600
"""How long a job's waiters are kept when its end never comes (a job that vanished): arq's own job lifetime."""


def waiters_key(job_id: str) -> str:
    """Set of the notice channels of the gateway processes waiting on `job_id`."""
    return f"{WAITERS_PREFIX}{job_id}"


def notice_channel(process: str) -> str:
    """The channel on which one gateway process hears of the ends of the jobs it waits on."""
    return f"{NOTICE_PREFIX}{process}"


NOTIFY_FUNCTION: Final = """
local function notify(waiters, record)
  for _, channel in ipairs(redis.call('SPOP', waiters, 2147483647)) do redis.call('PUBLISH', channel, record) end
end
"""
"""Lua: publish `record` (`record` below, or the job id alone) to every waiter of a job, forgetting them in the
same command (an SPOP of the whole set, which deletes it)."""

RECORD_FUNCTION: Final = """
local function record(id, progress, result, max_bytes)
  if not result or #result > tonumber(max_bytes) then return id end
  return id .. '\\n' .. (progress or '') .. '\\n' .. result
end
"""
"""Lua: a notice's text: the job id, its progress (JSON, no line break) and arq's result, on three lines."""


def read_notice(message: bytes) -> tuple[str, bytes | None, bytes | None]:
    """A notice's job id, and the progress and arq's result it carries (both None when it carries the id alone)."""
    job_id, sep, rest = message.partition(b"\n")
    if not sep:
        return job_id.decode(errors="replace"), None, None
    progress, _, result = rest.partition(b"\n")
    return job_id.decode(errors="replace"), progress, result
