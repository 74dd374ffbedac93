"""Worker heartbeats, and the hand-back of a dead worker's jobs that they make possible.

Expiring keys rather than a registry that workers join and leave: a SIGKILLed worker cannot say goodbye, and
its key (`precond:worker:<id>`) simply lapses `PRECOND_HEARTBEAT_TTL_S` after its last beat (3 beats by
default). Readiness and metrics read these keys.

Liveness-based recovery. The take marks a started job with `arq:in-progress:<job id>`, which expires only job
timeout + 10 s after the start (15 minutes by default); until then no worker runs the job again, even if
the worker running it was SIGKILLed a second after starting it. So every worker also records what it runs in
one hash, `precond:running`: job id → claim `<worker id>|<nonce>` (a nonce per run, so an old run's claim
is never mistaken for a new one's). The claim is written, together with a fresh heartbeat, by the script that
takes the job (`steps.take`: in one step with the job's in-progress key), and removed by the one that
records its end. On each beat a worker runs `_BEAT`, one Lua script (Redis runs it atomically, so two
workers never both act on one claim):

1. it rewrites its own heartbeat key, and adds the counts of the runs it ended since its last beat to the
   workers' stats (precond/jobs/records.py);
2. it re-registers the jobs it is running whose claims are gone (Redis restarted without them), never over
   another worker's claim;
3. it hands back the jobs it dropped itself, named by their runs' claims: runs that ended without their end
   recorded (Redis went away mid-job), and takes whose answer was lost (the script may have run: the claim
   then names a job this worker never learned);
4. for every other claim whose worker's heartbeat key has expired, and whose job is still in progress with
   no result, it deletes its in-progress key: the job is still in its queue, so the next take of any
   live worker runs it again (the try counted). Claims of finished jobs are dropped on the way;
5. it hands back jobs that were started but never claimed. When the in-progress key was set and the claim
   followed a few round trips later, a worker SIGKILLed in between left a started job that no claim named,
   which steps 1-4 never see, so it waited for the in-progress key's expiry (job timeout + 10 s): that is how
   `test_sigkilled_workers_lose_no_job` once lost a job. The take now writes both at once; this step stays
   for any in-progress key without a claim (one a Redis restart kept while losing the claims hash, or one
   written by a worker of an older version during an upgrade). Such a job is noted (`precond:unclaimed`,
   with the Redis time) by the first beat that sees it, and handed back by a beat a whole heartbeat lease
   later. A live worker's unclaimed job is claimed long before that (its own next beat re-registers it,
   step 2).

A live worker's jobs are never touched: its heartbeat key exists. The heartbeat runs on the worker's event
loop and the engine in a thread (precond/worker/jobs.py), so a long job does not stop the beats.
"""

from __future__ import annotations

import uuid
from collections.abc import Collection, Mapping
from typing import Any

from pydantic import BaseModel
from redis.asyncio import Redis

from precond.jobs.queue.keys import (
    IN_PROGRESS_PREFIX,
    QUEUES,
    RESULT_PREFIX,
    RUNNING_KEY,
    STATS_KEY,
    UNCLAIMED_KEY,
    WORKER_PREFIX,
    WORKERS_PATTERN,
    worker_key,
)
from precond.jobs.scripts import LuaScript


class Heartbeat(BaseModel):
    id: str
    host: str
    pid: int
    queues: list[str]
    model_loaded: bool
    model_error: str | None = None
    sandbox: str = "confined"
    """`confined`; `unconfined` (the development setting); `unavailable` (refuses all work)."""
    sandbox_error: str | None = None
    jobs_started: int = 0
    """Runs this worker process started (each try of a job counts); never decreases."""
    jobs_complete: int = 0
    """Runs that returned an outcome (a succeeded or a failed request); never decreases."""


_BEAT = LuaScript("""
local running, me, stats = KEYS[2], ARGV[1], KEYS[4]
local worker_prefix, progress_prefix, result_prefix = ARGV[4], ARGV[5], ARGV[6]
redis.call('SET', KEYS[1], ARGV[2], 'PX', ARGV[3])
local function unfinished(job)
  return redis.call('EXISTS', progress_prefix .. job) == 1 and redis.call('EXISTS', result_prefix .. job) == 0
end
local released = {}
local function hand_back(job)
  redis.call('DEL', progress_prefix .. job)
  table.insert(released, job)
end
local queues = {}
for q = 1, tonumber(ARGV[8]) do queues[q] = ARGV[8 + q] end
local i = 10 + #queues
for _ = 1, tonumber(ARGV[9 + #queues]) do  -- the counts this worker added up since its last beat
  redis.call('HINCRBYFLOAT', stats, ARGV[i], ARGV[i + 1])
  i = i + 2
end
for _ = 1, tonumber(ARGV[7]) do  -- jobs this worker runs: re-register those whose claim Redis lost
  if unfinished(ARGV[i]) then redis.call('HSETNX', running, ARGV[i], ARGV[i + 1]) end
  i = i + 2
end
local dropped = {}
while i <= #ARGV do  -- claims of runs this worker dropped: their jobs go back below, now
  dropped[ARGV[i]] = true
  i = i + 1
end
local unclaimed, lease = KEYS[3], tonumber(ARGV[3])
local clock = redis.call('TIME')
local now = tonumber(clock[1]) * 1000 + math.floor(tonumber(clock[2]) / 1000)
local seen = {}
for _, queue in ipairs(queues) do  -- step 5: started, never claimed
  for _, job in ipairs(redis.call('ZRANGE', queue, 0, -1)) do
    if unfinished(job) and redis.call('HEXISTS', running, job) == 0 then
      seen[job] = true
      local since = redis.call('HGET', unclaimed, job)
      if not since then
        redis.call('HSET', unclaimed, job, now)
      elseif now - tonumber(since) >= lease then
        hand_back(job)
        redis.call('HDEL', unclaimed, job)
        seen[job] = nil
      end
    end
  end
end
for _, job in ipairs(redis.call('HKEYS', unclaimed)) do
  if not seen[job] then redis.call('HDEL', unclaimed, job) end
end
local claims = redis.call('HGETALL', running)
for j = 1, #claims, 2 do
  local job, owner = claims[j], string.match(claims[j + 1], '^(.*)|')
  if not unfinished(job) then
    redis.call('HDEL', running, job)
  elseif dropped[claims[j + 1]] or (owner ~= me and redis.call('EXISTS', worker_prefix .. (owner or '')) == 0) then
    hand_back(job)
    redis.call('HDEL', running, job)
  end
end
return released
""")

def new_claim(worker_id: str) -> str:
    return f"{worker_id}|{uuid.uuid4().hex[:12]}"


def _pairs(items: Mapping[str, Any]) -> list[Any]:
    return [item for pair in items.items() for item in pair]


async def beat(
    redis: Redis[bytes],
    heartbeat: Heartbeat,
    ttl_s: float,
    running: dict[str, str] | None = None,
    dropped: Collection[str] = (),
    counts: Mapping[str, float] | None = None,
) -> list[str]:
    """One heartbeat (steps 1-5 above). `running` maps job ids to this worker's claims on them; `dropped` are
    claims of this worker's runs to hand back; `counts` are stats to add (records.PendingCounts).

    Returns the ids of the jobs handed back to the queue (a dead worker's, or dropped ones).
    """
    running, counts = running or {}, counts or {}
    args: list[Any] = [
        heartbeat.id,
        heartbeat.model_dump_json(),
        int(ttl_s * 1000),
        WORKER_PREFIX,
        IN_PROGRESS_PREFIX,
        RESULT_PREFIX,
        len(running),
        len(QUEUES),
        *QUEUES,
        len(counts),
        *_pairs(counts),
        *_pairs(running),
        *dropped,
    ]
    released = await _BEAT(redis, [worker_key(heartbeat.id), RUNNING_KEY, UNCLAIMED_KEY, STATS_KEY], args)
    return [job.decode() for job in released]


async def live_workers(redis: Redis[bytes]) -> list[Heartbeat]:
    keys = [key async for key in redis.scan_iter(match=WORKERS_PATTERN, count=100)]
    raws = await redis.mget(keys) if keys else []
    return [Heartbeat.model_validate_json(raw) for raw in raws if raw is not None]
