"""Worker heartbeats, and the hand-back of a dead worker's jobs that they make possible.

Expiring keys rather than a registry that workers join and leave: a SIGKILLed worker cannot say goodbye, and
its key (`precond:worker:<id>`) simply lapses `PRECOND_HEARTBEAT_TTL_S` after its last beat (3 beats by
default). Readiness and metrics read these keys.

Liveness-based recovery. arq marks a started job with `arq:in-progress:<job id>`, which expires only job
timeout + 10 s after the start (15 minutes by default); until then no worker runs the job again, even if
the worker running it was SIGKILLed a second after starting it. So every worker also records what it runs in
one hash, `precond:running`: job id → claim `<worker id>|<nonce>` (a nonce per run, so an old run's claim
is never mistaken for a new one's). The claim is written, together with a fresh heartbeat, when the job
starts (arq's `on_job_start`: after arq set its in-progress key), and removed when it ends. On each beat a
worker runs `_BEAT`, one Lua script (Redis runs it atomically, so two workers never both act on one claim):

1. it rewrites its own heartbeat key;
2. it re-registers the jobs it is running whose claims are gone (Redis restarted without them), never over
   another worker's claim;
3. it hands back the jobs it dropped itself (runs that ended without arq recording their end, as when Redis
   went away mid-job);
4. for every other claim whose worker's heartbeat key has expired, and whose job is still in progress with
   no result, it deletes arq's in-progress key: the job is still in arq's queue, so the next poll of any
   live worker runs it again (arq counts the try). Claims of finished jobs are dropped on the way;
5. it hands back jobs that were started but never claimed. arq sets a job's in-progress key when a worker
   takes it, and the claim follows a few Redis round trips later (`on_job_start`); a worker SIGKILLed in
   between leaves a started job that no claim names, which steps 1-4 never see, so it waited for arq's
   in-progress expiry (job timeout + 10 s): under load that window is wide enough to be hit, and it is
   how `test_sigkilled_workers_lose_no_job` lost a job. Such a job is noted (`precond:unclaimed`, with the
   Redis time) by the first beat that sees it, and handed back by a beat a whole heartbeat lease later. A
   live worker's unclaimed job is claimed long before that (its own next beat re-registers it, step 2).

A live worker's jobs are never touched: its heartbeat key exists. The heartbeat runs on the worker's event
loop and the engine in a thread (worker/jobs.py), so a long job does not stop the beats.
"""

from __future__ import annotations

import uuid
from typing import Any

from arq.constants import in_progress_key_prefix, result_key_prefix
from pydantic import BaseModel
from redis.asyncio import Redis

from jobs.keys import QUEUES, RUNNING_KEY, UNCLAIMED_KEY, WORKER_PREFIX, WORKERS_PATTERN, worker_key


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


_BEAT = """
local running, me = KEYS[2], ARGV[1]
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
local i = 9 + #queues
for _ = 1, tonumber(ARGV[7]) do  -- jobs this worker runs: re-register those whose claim Redis lost
  if unfinished(ARGV[i]) then redis.call('HSETNX', running, ARGV[i], ARGV[i + 1]) end
  i = i + 2
end
while i < #ARGV do  -- runs this worker dropped: hand their jobs back now
  if redis.call('HGET', running, ARGV[i]) == ARGV[i + 1] then
    if unfinished(ARGV[i]) then hand_back(ARGV[i]) end
    redis.call('HDEL', running, ARGV[i])
  end
  i = i + 2
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
  elseif owner ~= me and redis.call('EXISTS', worker_prefix .. (owner or '')) == 0 then
    hand_back(job)
    redis.call('HDEL', running, job)
  end
end
return released
"""

_RELEASE = """
if redis.call('HGET', KEYS[1], ARGV[1]) == ARGV[2] then return redis.call('HDEL', KEYS[1], ARGV[1]) end
return 0
"""


def new_claim(worker_id: str) -> str:
    return f"{worker_id}|{uuid.uuid4().hex[:12]}"


def _pairs(claims: dict[str, str]) -> list[str]:
    return [item for pair in claims.items() for item in pair]


async def beat(
    redis: Redis[bytes],
    heartbeat: Heartbeat,
    ttl_s: float,
    running: dict[str, str] | None = None,
    dropped: dict[str, str] | None = None,
) -> list[str]:
    """One heartbeat (steps 1-4 above). `running` and `dropped` map job ids to this worker's claims.

    Returns the ids of the jobs handed back to the queue (a dead worker's, or dropped ones).
    """
    running, dropped = running or {}, dropped or {}
    args: list[Any] = [
        heartbeat.id,
        heartbeat.model_dump_json(),
        int(ttl_s * 1000),
        WORKER_PREFIX,
        in_progress_key_prefix,
        result_key_prefix,
        len(running),
        len(QUEUES),
        *QUEUES,
        *_pairs(running),
        *_pairs(dropped),
    ]
    released = await redis.eval(_BEAT, 3, worker_key(heartbeat.id), RUNNING_KEY, UNCLAIMED_KEY, *args)  # type: ignore[no-untyped-call]
    return [job.decode() for job in released]


async def claim(redis: Redis[bytes], heartbeat: Heartbeat, ttl_s: float, job_id: str, token: str) -> None:
    """Record that this worker runs `job_id`, with a fresh heartbeat: no claim without a live heartbeat."""
    async with redis.pipeline(transaction=True) as pipe:
        pipe.set(worker_key(heartbeat.id), heartbeat.model_dump_json(), px=int(ttl_s * 1000))
        pipe.hset(RUNNING_KEY, job_id, token)
        await pipe.execute()


async def release(redis: Redis[bytes], job_id: str, token: str) -> None:
    """Remove this run's claim on `job_id` (not a later run's, perhaps on another worker)."""
    await redis.eval(_RELEASE, 1, RUNNING_KEY, job_id, token)  # type: ignore[no-untyped-call]


async def live_workers(redis: Redis[bytes]) -> list[Heartbeat]:
    keys = [key async for key in redis.scan_iter(match=WORKERS_PATTERN, count=100)]
    raws = await redis.mget(keys) if keys else []
    return [Heartbeat.model_validate_json(raw) for raw in raws if raw is not None]
