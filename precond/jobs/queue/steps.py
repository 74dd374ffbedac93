"""Each step of a job's life as one Lua script that Redis runs atomically, and the typed call that runs it.

submit (the gateway: bound, fair place, enqueue, waiter, wake-up), cancel a queued job (the gateway), mark a
running one for abort (the gateway), take the next job (a worker: in-progress mark, try count and claim under a
fresh heartbeat), finish a run (a worker: its end, the claim's release and the completion notice).
The hand-back of a dead worker's jobs is the heartbeat's script (`precond.jobs.queue.heartbeats`). Every write to
a queue's keys is one of these; tests/jobs/test_queue_contract.py runs them in order against a real Redis.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timedelta
from typing import Final

from redis.asyncio import Redis

from precond.jobs.queue.keys import (
    ABORTS_KEY,
    IN_PROGRESS_PREFIX,
    JOB_PREFIX,
    RESULT_PREFIX,
    RETRY_PREFIX,
    RUNNING_KEY,
    STATE_TTL_S,
    JobId,
    fair_key,
    progress_key,
    tenant_jobs_key,
    wake_channel,
    worker_key,
)
from precond.jobs.queue.notices import NOTIFY_FUNCTION, RECORD_FUNCTION, RECORD_MAX_BYTES, WAITERS_TTL_S, waiters_key
from precond.jobs.scripts import LuaScript

FAIR_EPOCH_MS: Final = 946_684_800_000  # 2000-01-01: every fair score is in the past, so due at once
JOB_EXPIRY: Final = timedelta(days=1)
"""How long a queued job may wait before its bytes expire (a worker then ends it failed, `job expired`)."""
RETRY_KEY_TTL_S: Final = 88_400
"""Lifetime of a job's try count."""
CANCEL_GUARD: Final = b"cancelled"
CANCEL_GUARD_MS: Final = 2000

# A tenant's unfinished jobs: the count of the tenant's live jobs when it has `limit` already, else -1 (a job
# the tenant already has, an identical request, is free). The step that ends a job takes it out of the set; ids
# whose job key is gone without one (a job's bytes that expired) leave the set only once it looks full, so that
# the common case, a tenant under its cap, costs one ZCARD.
TENANT_JOBS_FUNCTION: Final = """
local function tenant_full(jobs, id, limit, job_prefix)
  if redis.call('ZCARD', jobs) < tonumber(limit) or redis.call('ZSCORE', jobs, id) then return -1 end
  for _, other in ipairs(redis.call('ZRANGE', jobs, 0, -1)) do
    if redis.call('EXISTS', job_prefix .. other) == 0 then redis.call('ZREM', jobs, other) end
  end
  local count = redis.call('ZCARD', jobs)
  if count >= tonumber(limit) then return count end
  return -1
end
"""

# Fair ordering: a job's score is its tenant's virtual start time, one more than the larger of the queue's head
# and the tenant's last job (docs/tenants.md). Virtual time is the queue's head score; with nothing queued, the
# highest score handed out so far (all of those jobs are done, so a tenant's old backlog gives it no head start
# and no debt). Scores count up from a fixed epoch long past, so every job is due at once.
FAIR_SCORE_FUNCTION: Final = """
local function fair_score(queue, fair, tag, epoch, ttl)
  local head = redis.call('ZRANGE', queue, 0, 0, 'WITHSCORES')
  local last = redis.call('HMGET', fair, '~max', tag)
  local highest = tonumber(last[1] or epoch)
  local clock = highest
  if head[2] then
    clock = tonumber(head[2])
  end
  local score = math.max(clock, tonumber(last[2] or 0)) + 1
  redis.call('HSET', fair, tag, score, '~max', math.max(highest, score))
  redis.call('EXPIRE', fair, ttl)
  return score
end
"""

_SUBMIT = LuaScript("#!lua\n" + FAIR_SCORE_FUNCTION + TENANT_JOBS_FUNCTION + """
local full = tenant_full(KEYS[6], ARGV[1], ARGV[9], ARGV[10])
if full >= 0 then return -2 - full end
if redis.call('exists', KEYS[4], KEYS[3]) > 0 then
  if redis.call('exists', KEYS[4]) == 1 then return 0 end
  redis.call('sadd', KEYS[7], ARGV[12])
  redis.call('expire', KEYS[7], ARGV[13])
  return 0
end
if redis.call('zcard', KEYS[1]) >= tonumber(ARGV[2]) then return -1 end
redis.call('zrem', KEYS[5], ARGV[1])
local score = fair_score(KEYS[1], KEYS[2], ARGV[3], ARGV[4], ARGV[5])
redis.call('psetex', KEYS[3], ARGV[7], ARGV[6])
redis.call('zadd', KEYS[1], score, ARGV[1])
redis.call('zadd', KEYS[6], ARGV[11], ARGV[1])
redis.call('expire', KEYS[6], ARGV[5])
redis.call('sadd', KEYS[7], ARGV[12])
redis.call('expire', KEYS[7], ARGV[13])
redis.call('publish', ARGV[8], '1')
return 1
""")
"""`-2 - n` when its tenant has `n` jobs queued or running, its cap; 0 when the same job exists (queued, running or
with a result: identical requests share it); -1 when the queue holds `max_jobs` already; else 1. The step counts
the job as its tenant's, clears a stale abort mark of the id (arq#485), gives the job its tenant's fair place,
names the waiting gateway process among the job's waiters (unless its end is stored already: notices.py) and
wakes an idle worker (advisory: workers still poll). Atomic, so concurrent submissions, from any number of gateway
processes, never push a queue or a tenant past its bound. Declared (`#!lua`, Redis 7), so a Redis at its
`maxmemory` refuses the whole step before it starts (503); undeclared, Redis refuses only a script whose first
write needs memory, and a first write that frees some (a stale abort mark, a finished job's place in its tenant's
set) let the rest enqueue past the limit."""

_DROP_GUARD = LuaScript("""
if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end
return 0
""")

_CANCEL_QUEUED = LuaScript(NOTIFY_FUNCTION + """
if redis.call('exists', KEYS[3]) == 1 or redis.call('exists', KEYS[5]) == 1 then return 0 end
if redis.call('zrem', KEYS[1], ARGV[1]) == 0 then return 0 end
redis.call('del', KEYS[2], KEYS[4])
redis.call('zrem', KEYS[6], ARGV[1])
redis.call('zrem', KEYS[8], ARGV[1])
redis.call('set', KEYS[3], ARGV[4], 'PX', ARGV[5])
redis.call('set', KEYS[5], ARGV[2], 'PX', ARGV[3])
notify(KEYS[7], ARGV[1])
return 1
""")
"""Out of its queue and its tenant's jobs, its result `cancelled`, its waiters told. The in-progress key is set
briefly to a guard value, so that a worker's take, which starts only jobs without one, cannot start it."""

_TAKE = LuaScript("""
local aborts = redis.call('ZRANGE', KEYS[2], 0, -1)
if ARGV[11] ~= '1' then return {aborts} end
local skip = {}
for i = 12, #ARGV do skip[ARGV[i]] = true end
local queued = redis.call('ZRANGEBYSCORE', KEYS[1], '-inf', ARGV[1], 'WITHSCORES', 'LIMIT', 0, ARGV[6])
for n = 1, #queued, 2 do
  local id = queued[n]
  local tenant = string.match(id, '%-([^-]+)%-[^-]+$')
  if not skip[tenant] and redis.call('SET', ARGV[8] .. id, '1', 'PX', ARGV[2], 'NX') then
    local job = redis.call('GET', ARGV[9] .. id)
    local try = redis.call('INCR', ARGV[10] .. id)
    redis.call('EXPIRE', ARGV[10] .. id, ARGV[7])
    local aborted = 0
    for _, mark in ipairs(aborts) do
      if mark == id then aborted = redis.call('ZREM', KEYS[2], id) end
    end
    redis.call('SET', KEYS[3], ARGV[3], 'PX', ARGV[4])
    redis.call('HSET', KEYS[4], id, ARGV[5])
    return {aborts, id, queued[n + 1], job, try, aborted, #queued > 2 and 1 or 0}
  end
end
return {aborts}
""")
"""The abort marks (for the runs going on in the worker), and, when it has a free slot (ARGV[11]), the next job it
may start, taken: the first of the queue's due jobs (in fair-score order, up to the read limit) that no worker
started (no in-progress key: none runs it, no cancellation guards it) and whose tenant is not skipped (ARGV[12..]:
the tenants at their share in the worker; the tenant is the id's part between its last two dashes, keys.job_id).
The take sets the in-progress key (where none is: one SET NX), counts the try and claims the job under a fresh
heartbeat (heartbeats.py) in one step, so no worker can die between the two and leave a started job that no claim
names; the job's own abort mark, if any, is found among the marks read and forgotten. Returns the abort marks,
then the job's id, score, bytes (false once expired), try, whether an abort mark waited for it, and whether the
read saw other jobs."""

_FINISH = LuaScript(NOTIFY_FUNCTION + RECORD_FUNCTION + """
if ARGV[2] == '1' then
  if ARGV[3] ~= '' then redis.call('SET', KEYS[1], ARGV[3], 'PX', ARGV[4]) end
  redis.call('DEL', KEYS[2], KEYS[3], KEYS[4])
  redis.call('ZREM', KEYS[5], ARGV[1])
  redis.call('ZREM', KEYS[6], ARGV[1])
  redis.call('ZREM', KEYS[10], ARGV[1])
else
  redis.call('DEL', KEYS[2])
end
if redis.call('HGET', KEYS[7], ARGV[1]) == ARGV[5] then redis.call('HDEL', KEYS[7], ARGV[1]) end
local result = false
if ARGV[2] == '1' and ARGV[3] ~= '' then result = ARGV[3] end
local progress = false
if ARGV[7] == '1' then progress = redis.call('GET', KEYS[8]) end
notify(KEYS[9], record(ARGV[1], progress, result, ARGV[6]))
return redis.call('ZCARD', KEYS[6])
""")
"""Finished: its result stored, its keys gone and it no longer its tenant's; not finished (a shutdown cancelled it):
its in-progress key gone, so that the job, still queued, runs again. With it, this run's claim released (not a
later run's), and the notice to the gateway processes that wait on the job, carrying its end as stored
(notices.py). Returns how many jobs the queue holds now (queued, or running elsewhere)."""


class QueueFull(Exception):
    """The job's queue holds `max_jobs` already; the client should come back later (429)."""


class TenantFull(Exception):
    """The tenant has its cap of jobs queued or running (`count` of them); it should come back later (429)."""

    def __init__(self, count: int) -> None:
        super().__init__(count)
        self.count = count


@dataclass(frozen=True)
class Submission:
    """One job to enqueue: its bytes (payloads.encode_job) and where and for whom it goes."""

    queue: str
    job_id: str
    tenant: str
    job: bytes
    enqueued_ms: int
    waiter: str
    """The notice channel of the gateway process that waits on it (notices.notice_channel)."""


async def submit(redis: Redis[bytes], job: Submission, max_jobs: int, tenant_max_jobs: int) -> bool:
    """Enqueue `job` unless the same job exists (False); TenantFull or QueueFull past a bound."""
    code = int(await _SUBMIT(
        redis,
        [job.queue, fair_key(job.queue), JOB_PREFIX + job.job_id, RESULT_PREFIX + job.job_id, ABORTS_KEY,
         tenant_jobs_key(job.tenant), waiters_key(job.job_id)],
        [job.job_id, max_jobs, job.tenant, FAIR_EPOCH_MS, STATE_TTL_S, job.job,
         int(JOB_EXPIRY.total_seconds() * 1000), wake_channel(job.queue), tenant_max_jobs, JOB_PREFIX,
         job.enqueued_ms / 1000, job.waiter, WAITERS_TTL_S],
    ))
    if code <= -2:
        raise TenantFull(-2 - code)
    if code < 0:
        raise QueueFull(job.queue)
    return code == 1


async def reopen(redis: Redis[bytes], job_id: str) -> None:
    """Forget an ended job's stored end (and a cancellation's guard), so that the next submit runs it again."""
    await redis.delete(RESULT_PREFIX + job_id)
    await _DROP_GUARD(redis, [IN_PROGRESS_PREFIX + job_id], [CANCEL_GUARD])


async def cancel_queued(redis: Redis[bytes], queue: str, job_id: str, cancelled: bytes, result_ttl_ms: int) -> bool:
    """Cancel a job no worker has started, storing `cancelled` (payloads.encode_result) as its end; False when it
    is not queued (started, ended, unknown)."""
    return bool(await _CANCEL_QUEUED(
        redis,
        [queue, JOB_PREFIX + job_id, IN_PROGRESS_PREFIX + job_id, RETRY_PREFIX + job_id, RESULT_PREFIX + job_id,
         ABORTS_KEY, waiters_key(job_id), _tenant_jobs_of(job_id)],
        [job_id, cancelled, result_ttl_ms, CANCEL_GUARD, CANCEL_GUARD_MS],
    ))


async def mark_abort(redis: Redis[bytes], queue: str, job_id: str, now_ms: int) -> None:
    """Mark a running job for abort, and wake its queue's workers to read the mark."""
    async with redis.pipeline(transaction=False) as pipe:
        pipe.zadd(ABORTS_KEY, {job_id: now_ms})
        pipe.publish(wake_channel(queue), b"1")
        await pipe.execute()


async def clear_aborts(redis: Redis[bytes], job_ids: set[str]) -> None:
    """Forget the abort marks of runs a worker cancelled."""
    if job_ids:
        await redis.zrem(ABORTS_KEY, *job_ids)


@dataclass(frozen=True)
class Claim:
    """A worker's claim on one run (`<worker id>|<nonce>`), and the heartbeat written with it."""

    worker: str
    token: str
    heartbeat: str
    lease_ms: int


@dataclass(frozen=True)
class Taken:
    id: str
    score: int
    job: bytes | None
    job_try: int
    aborted: bool


@dataclass(frozen=True)
class Take:
    """What one take reads: the queue, up to `read_limit` due jobs of it, and the in-progress mark's lifetime."""

    queue: str
    worker_id: str
    read_limit: int
    in_progress_ms: int


async def take(redis: Redis[bytes], how: Take, now_ms: int, claim: Claim | None, skip_tags: list[str]
               ) -> tuple[list[bytes], Taken | None, bool]:
    """The abort marks, and (under `claim`; None: only the marks) the next job, skipping the tenants named by
    `skip_tags`; and whether the read saw other jobs."""
    heartbeat, lease_ms, token = (claim.heartbeat, claim.lease_ms, claim.token) if claim else ("", 0, "")
    answer = await _TAKE(
        redis, [how.queue, ABORTS_KEY, worker_key(how.worker_id), RUNNING_KEY],
        [now_ms, how.in_progress_ms, heartbeat, lease_ms, token, how.read_limit, RETRY_KEY_TTL_S,
         IN_PROGRESS_PREFIX, JOB_PREFIX, RETRY_PREFIX, "1" if claim else "0", *skip_tags],
    )
    if len(answer) == 1:
        return answer[0], None, False
    aborts, job_id, score, job, job_try, aborted, more = answer
    return aborts, Taken(job_id.decode(), int(float(score)), job or None, int(job_try), bool(aborted)), bool(more)


@dataclass(frozen=True)
class Finish:
    """A run's end: `finished` False hands the job back to its queue (a shutdown cancelled the run); `stored` is
    its end (payloads.encode_result), kept `keep_result_ms`; `progressed` False for a run that wrote no progress
    (its notice then carries none, unread). The run's stats go with the worker's next heartbeat
    (records.PendingCounts), not with its end."""

    queue: str
    job_id: str
    claim_token: str
    finished: bool
    stored: bytes | None
    keep_result_ms: int
    progressed: bool = True


async def finish(redis: Redis[bytes], end: Finish) -> int:
    """Record a run's end (`_FINISH`); how many jobs its queue holds now."""
    job_id = end.job_id
    return int(await _FINISH(
        redis,
        [RESULT_PREFIX + job_id, IN_PROGRESS_PREFIX + job_id, RETRY_PREFIX + job_id, JOB_PREFIX + job_id,
         ABORTS_KEY, end.queue, RUNNING_KEY, progress_key(job_id), waiters_key(job_id), _tenant_jobs_of(job_id)],
        [job_id, "1" if end.finished else "0", end.stored or b"", end.keep_result_ms, end.claim_token,
         RECORD_MAX_BYTES, "1" if end.progressed else "0"],
    ))


def _tenant_jobs_of(job_id: str) -> str:
    """The set of the unfinished jobs of the id's tenant (an id this service never hands out names no tenant's,
    and was never counted as one's)."""
    identity = JobId.read(job_id)
    return tenant_jobs_key(identity.tenant if identity else "")
