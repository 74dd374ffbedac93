"""Processes that end with the process that started them.

`precond serve` starts redis-servers, gateways and workers; a gateway starts its check pool (and, through
multiprocessing, a resource tracker); a worker starts a training process. Killed with SIGKILL, a parent cannot
stop what it started, and its children would run on, orphaned, holding ports, memory and Redis connections.
The kernel's parent-death signal ends them instead: set in the child, it fires when the thread that started
the child ends. A resource tracker ends by itself once every process holding its pipe is gone.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent: int) -> None:
    """Ask the kernel to SIGKILL this process when its parent ends; exit now if `parent` (the pid that started
    this process) is already gone, since the signal only covers a death after it is set. Where the call does
    not exist (not Linux) the process lives on as before: this keeps a machine clean, it confines nothing."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(1)
