"""The job protocol that gateway (`precond.gateway`) and queue worker (`precond.worker`) both speak, and all they share.

Queue names, job ids and Redis keys (`jobs.keys`), heartbeats and claims (`jobs.heartbeats`), the result
cache (`jobs.cache`), the typed records a worker writes and the gateway reads (`jobs.records`: outcome,
progress, stats) and the settings both deployables must read alike (`jobs.settings.QueueSettings`; each one's own
are `precond/gateway/settings.py` and `precond/worker/settings.py`). `precond/gateway/` and `precond/worker/` import
this package and never each other (tests/test_layers.py checks it).
"""
