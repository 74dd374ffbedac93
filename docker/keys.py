"""Compose's one-shot `keys` service: writes each named secret file once, with a fresh random value.

    python docker/keys.py /secrets/redis-password /secrets/precond-secret

A file that exists is kept (secrets survive `docker compose up` after `down`); a new one is created
exclusively with mode 0600, so two runs at once never write different values. Standard library only, like
docker/healthcheck.py.
"""

from __future__ import annotations

import os
import secrets
import sys
from pathlib import Path


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


if __name__ == "__main__":
    for name in sys.argv[1:]:
        print(f"{name}: {'created' if ensure(Path(name)) else 'kept'}")
