"""Compose's one-shot `keys` service: writes each named secret file once, with a fresh random value, and the
Redis servers' users.

    python docker/keys.py /secrets/precond-secret --redis /secrets

A file that exists is kept (secrets survive `docker compose up` after `down`); a new one is created
exclusively with mode 0600, so two runs at once never write different values. `--redis DIR` does the same for
the password of each Redis user (`redis-<server>-<role>-password`: precond/jobs/redis_roles.py) and writes each
Redis's ACL lines (`redis-<server>.acl`: the passwords as SHA-256) from them, and the KEDA user's name
(`redis-queue-keda-username`, for its TriggerAuthentication). Standard library and that module only, like
docker/healthcheck.py.
"""

from __future__ import annotations

import argparse
import os
import secrets
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a checkout, where the package is not installed

from precond.jobs.redis_roles import ROLES, acl_file, acl_lines, password_file


def ensure(path: Path) -> bool:
    """Create `path` with a random hex value unless it exists; True if it was created."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as out:
        out.write(secrets.token_hex(32) + "\n")
    return True


def redis_users(directory: Path) -> None:
    """Each Redis user's password (kept when it exists), then each Redis's ACL lines from them (rewritten, so
    that they follow the roles of this release)."""
    for server, roles in ROLES.items():
        passwords = {}
        for role in roles:
            path = directory / password_file(server, role)
            print(f"{path}: {'created' if ensure(path) else 'kept'}")
            passwords[role] = path.read_text().strip()
        write(directory / acl_file(server), "\n".join(acl_lines(server, passwords)) + "\n")
    write(directory / "redis-queue-keda-username", "keda")


def write(path: Path, text: str) -> None:
    """Replace `path` at once (a Redis that starts meanwhile reads the old file or the new one, never half)."""
    partial = path.with_name(f".{path.name}.{os.getpid()}")
    fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as out:
        out.write(text)
    partial.replace(path)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="*", type=Path, help="secret files, each a random value")
    parser.add_argument("--redis", type=Path, metavar="DIR", help="the Redis users' passwords and ACL lines")
    args = parser.parse_args()
    for name in args.files:
        print(f"{name}: {'created' if ensure(name) else 'kept'}")
    if args.redis is not None:
        redis_users(args.redis)
