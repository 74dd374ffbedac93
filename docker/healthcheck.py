"""Container healthcheck: `gateway` asks /health, `worker` looks for this container's heartbeat in Redis.

Standard library plus redis only, and no import of the service, so a wedged app cannot wedge its check.
"""

from __future__ import annotations

import os
import socket
import sys
import urllib.request
from pathlib import Path


def gateway() -> bool:
    with urllib.request.urlopen("http://127.0.0.1:8000/health", timeout=3) as answer:
        return bool(answer.status == 200)


def worker() -> bool:
    import redis

    password_file = os.environ.get("PRECOND_REDIS_PASSWORD_FILE")  # used when the URL carries no password
    password = Path(password_file).read_text().strip() if password_file else None
    url = os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0")
    client = redis.Redis.from_url(url, password=password, socket_timeout=3)
    return bool(client.keys(f"precond:worker:{socket.gethostname()}-*"))


if __name__ == "__main__":
    sys.exit(0 if {"gateway": gateway, "worker": worker}[sys.argv[1]]() else 1)
