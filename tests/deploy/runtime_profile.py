"""Run a program under a seccomp profile of the kind a container runtime installs before the container's
first process starts (the sandbox's own filter then stacks on top of it):

    python runtime_profile.py runtime-default PROGRAM ARGS...   # namespaces and mounts denied, as the
                                                                # runtimes' default profile does without
                                                                # CAP_SYS_ADMIN
    python runtime_profile.py no-seccomp PROGRAM ARGS...        # a custom profile that forbids installing
                                                                # seccomp filters

Standard library and pyseccomp only, so it runs from a copy as any user.
"""

from __future__ import annotations

import errno
import os
import sys

import pyseccomp

CLONE_NEWUSER = 0x10000000
PR_SET_SECCOMP = 22


def profile(name: str) -> pyseccomp.SyscallFilter:
    rules = pyseccomp.SyscallFilter(defaction=pyseccomp.ALLOW)
    denied = pyseccomp.ERRNO(errno.EPERM)
    if name == "runtime-default":
        for call in ("unshare", "setns", "mount", "umount2", "pivot_root"):
            rules.add_rule(denied, call)
        rules.add_rule(denied, "clone", pyseccomp.Arg(0, pyseccomp.MASKED_EQ, CLONE_NEWUSER, CLONE_NEWUSER))
    elif name == "no-seccomp":
        rules.add_rule(denied, "seccomp")
        rules.add_rule(denied, "prctl", pyseccomp.Arg(0, pyseccomp.EQ, PR_SET_SECCOMP))
    else:
        raise SystemExit(f"unknown profile {name}")
    return rules


if __name__ == "__main__":
    profile(sys.argv[1]).load()
    os.execv(sys.argv[2], sys.argv[2:])
