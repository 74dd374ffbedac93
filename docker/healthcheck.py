"""Container healthcheck: `gateway` asks /health, `worker` looks for this container's heartbeat in Redis, and
`worker-ready` also reads what the heartbeat says: a worker whose sandbox cannot confine untrusted code (a pod
without what the sandbox needs) or whose model is not loaded is alive but not ready, and the check prints why
(the orchestrator shows it in the probe's failure event).

Standard library plus redis only, and no import of the service, so a wedged app cannot wedge its check.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import urllib.request
from pathlib import Path
from typing import Any

SERVING_QUEUE = "precond:queue:model"
"""precond.jobs.queue.keys.MODEL_QUEUE, spelt out here (tests/deploy checks that they agree): a worker reading it
loads the model; one reading only the training queue never does (each training loads its own, in a process of
its own), so it is ready without it."""


def gateway() -> bool:
    with urllib.request.urlopen("http://127.0.0.1:8000/health", timeout=3) as answer:
        return bool(answer.status == 200)


def heartbeats() -> list[dict[str, Any]]:
    """The heartbeats of this container's worker processes (keyed `precond:worker:<hostname>-<pid>-...`)."""
    import redis

    password_file = os.environ.get("PRECOND_REDIS_PASSWORD_FILE")  # used when the URL carries no password
    password = Path(password_file).read_text().strip() if password_file else None
    url = os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0")
    client = redis.Redis.from_url(url, password=password, socket_timeout=3)
    keys = list(client.scan_iter(match=f"precond:worker:{socket.gethostname()}-*"))  # SCAN: KEYS is no role's
    return [json.loads(raw) for raw in client.mget(keys) if raw] if keys else []


def worker() -> bool:
    return bool(heartbeats())


def not_ready(beat: dict[str, Any]) -> str | None:
    """Why this worker must not count as ready, or None."""
    if beat.get("sandbox") == "unavailable":
        reason = beat.get("sandbox_error")
        return f"the sandbox cannot confine untrusted code here, so this worker takes no job: {reason}"
    if SERVING_QUEUE in beat.get("queues", []) and not beat.get("model_loaded"):
        return f"the model is not loaded ({beat.get('model_error') or 'still loading'})"
    return None


def worker_ready() -> bool:
    beats = heartbeats()
    if not beats:
        print("no heartbeat of this worker in Redis")
        return False
    reasons = [reason for reason in map(not_ready, beats) if reason]
    for reason in reasons:
        print(reason)
    return not reasons


if __name__ == "__main__":
    checks = {"gateway": gateway, "worker": worker, "worker-ready": worker_ready}
    sys.exit(0 if checks[sys.argv[1]]() else 1)
