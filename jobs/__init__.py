"""The job protocol that gateway (`service/`) and queue worker (`worker/`) both speak, and all they share.

Queue names, job ids and Redis keys (`jobs.keys`), heartbeats and claims (`jobs.heartbeats`), the result
cache (`jobs.cache`), the typed records a worker writes and the gateway reads (`jobs.records`: outcome,
progress, stats) and the settings both deployables must read alike (`jobs.settings.QueueSettings`; each one's own
are `service/settings.py` and `worker/settings.py`). `service/` and `worker/` import
this package and never each other (tests/test_layers.py checks it).
"""
