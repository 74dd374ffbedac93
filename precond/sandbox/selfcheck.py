"""The sandbox's self-check as a program: can untrusted code be confined here, as this user, with these
capabilities, under this seccomp profile? It starts one fork server, whose probe child confines itself and
tries what the boundary forbids (precond/sandbox/child/server.py), and prints one JSON object: the answer,
why not, and the identity it ran under (uid, capabilities, no_new_privs, the process's own seccomp mode).
Exit status 0 when confined, 1 when not: the worker refuses every job in that case.

`precond sandbox-check` runs it in a container (`kubectl exec deploy/precond-worker -- precond sandbox-check`);
as `python -m precond.sandbox.selfcheck` it needs only the sandbox and the standard library.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from precond.sandbox.api import Sandbox
from precond.sandbox.types import SandboxUnavailable

STATUS_FIELDS = ("CapEff", "CapPrm", "CapBnd", "NoNewPrivs", "Seccomp")


def identity() -> dict[str, object]:
    """Who this process is, as the kernel sees it."""
    status = dict(line.split(":\t", 1) for line in Path("/proc/self/status").read_text().splitlines() if ":\t" in line)
    return {"uid": os.getuid(), "gid": os.getgid(), "groups": os.getgroups(),
            **{name: status.get(name, "?").strip() for name in STATUS_FIELDS}}


def check() -> dict[str, object]:
    try:
        with Sandbox(workers=1) as sandbox:
            found = sandbox.boundary
    except SandboxUnavailable as exc:
        found = {"confined": False, "reason": str(exc)}
    return {**found, "identity": identity()}


def main() -> int:
    report = check()
    print(json.dumps(report))
    return 0 if report["confined"] else 1


if __name__ == "__main__":
    sys.exit(main())
