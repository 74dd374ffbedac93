"""The job queue's contract, all of it: what gateway and workers write to Redis for a job, and in which steps.

The project owns its queue. Its keys (`keys`), the bytes of a queued job and of a stored end (`payloads`), the
routing of each job kind (`kinds`), the Lua script of each step of a job's life with the typed call that runs it
(`steps`: submit, cancel, mark for abort, take, finish), the completion notices (`notices`) and the hand-back of
a dead worker's jobs (`heartbeats`) are defined here and nowhere else; the gateway (precond/gateway/queue.py) and
the worker's loop (precond/worker/queue_worker.py) only call them. No queue library's worker runs, and no
library's private method is overridden or called.

arq remains for its key layout only (`arq.constants`, its public names). The records under those keys (a job, its
progress, its end) are the project's own: JSON validated by versioned pydantic models (`payloads`), whose JSON
Schema is openapi/queue-records.schema.json; a record that fails it ends its job failed, unread.

Why one script per step: a check's work takes a millisecond, and the round trips around it were most of its
latency (one script each for take and finish instead of seven round trips, one for submit instead of eight).
Every script is atomic, so any number of gateway processes and workers share one Redis without a lock.
tests/jobs/test_queue_contract.py runs a job through submit → take → finish → cancel → hand-back against a real
redis-server.
"""
