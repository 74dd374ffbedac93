"""The job protocol that gateway (`precond.gateway`) and queue worker (`precond.worker`) both speak, and all they share.

The queue's contract (`jobs.queue`: keys, job ids, payloads, the Lua script of each step of a job's life,
completion notices, heartbeats and the hand-back), the result cache (`jobs.cache`), the typed records a worker
writes and the gateway reads (`jobs.records`: outcome, progress, stats), and the settings both deployables must
read alike (`jobs.settings.QueueSettings`; each one's own are `precond/gateway/settings.py` and
`precond/worker/settings.py`). What tenants keep is `precond.store`, above this package; the libraries' patches are
`precond.patches`. `precond/gateway/` and `precond/worker/` import this package and never each other
(tests/test_layers.py checks it).
"""
