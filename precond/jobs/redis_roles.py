"""Who may do what on each Redis: one Redis ACL user per client role, with a password of its own.

The queue Redis holds what the service owes (jobs, their records, results, stored sets); the cache Redis only
signed cache entries. A credential opens one Redis for one role, never both Redis:

- queue `gateway`, `worker`: the service's own commands, on every key and channel; never an admin or dangerous
  command (CONFIG, DEBUG, KEYS, FLUSHALL, MODULE, ...).
- queue `keda`: KEDA's Redis scaler reads a queue's length, with one Lua script (TYPE, then ZCARD or LLEN) on the
  queue keys only. It may send EVAL, but Redis checks every command a script calls against the user: a script
  that reads a job's record, writes or publishes is refused (NOPERM). Nothing else.
- cache `gateway`, `worker`: GET, SET and DEL on the cache's keys, nothing else (no script, no queue command).
- `probe` on each: PING only, for the Redis servers' own health checks.
- `default`: off, so a connection that does not name a user can do nothing.

Standard library only: docker/keys.py (compose's one-shot `keys` service, and the Secret an operator makes for
Kubernetes) writes each role's password file and each Redis's ACL lines from here, and the tests start a real
redis-server with these lines (tests/deploy/test_redis_acl.py).
"""

from __future__ import annotations

import hashlib
from typing import Final

QUEUE_KEYS: Final = "~precond:queue:*"
CACHE_KEYS: Final = "~precond:cache:*"
CONNECT: Final = "+hello +ping"
"""What a client may send on connecting and for its health check (the CLIENT SETINFO that redis-py and go-redis
also send is refused, and both go on without it)."""

SERVICE: Final = "~* &* +@all -@admin -@dangerous"
ROLES: Final[dict[str, dict[str, str]]] = {
    "queue": {
        "gateway": SERVICE,
        "worker": SERVICE,
        "keda": f"resetkeys {QUEUE_KEYS} resetchannels -@all {CONNECT} +eval +type +zcard +llen",
        "probe": "resetkeys resetchannels -@all +ping",
    },
    "cache": {
        "gateway": f"resetkeys {CACHE_KEYS} resetchannels -@all {CONNECT} +get +set +del",
        "worker": f"resetkeys {CACHE_KEYS} resetchannels -@all {CONNECT} +get +set +del",
        "probe": "resetkeys resetchannels -@all +ping",
    },
}
"""Each Redis's users: role → the ACL rules of its user (the user's name is the role's)."""
DEFAULT_OFF: Final = "user default off resetpass resetkeys resetchannels -@all"


def password_file(server: str, role: str) -> str:
    """The name of the file (and Secret key) holding `role`'s password on `server`."""
    return f"redis-{server}-{role}-password"


def acl_file(server: str) -> str:
    """The name of the file (and Secret key) holding `server`'s ACL lines."""
    return f"redis-{server}.acl"


def acl_lines(server: str, passwords: dict[str, str]) -> list[str]:
    """`server`'s users as redis.conf / ACL-file lines, each password given as its SHA-256 (the Redis server
    never holds a password in clear)."""
    lines = [DEFAULT_OFF]
    for role, rules in ROLES[server].items():
        digest = hashlib.sha256(passwords[role].encode()).hexdigest()
        lines.append(f"user {role} on #{digest} {rules}")
    return lines
