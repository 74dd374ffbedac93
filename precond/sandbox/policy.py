"""The seccomp allowlist every sandbox child runs under, built here with libseccomp (via pyseccomp).

Built in the worker, where libseccomp resolves syscall names for the running architecture and emits a
BPF program; the fork server receives the program as bytes and installs it in each child with one prctl.
The child's interpreter (``python -I -S``) never needs a binding of its own, and the filter is reviewable
in one list below. Everything not listed fails with EPERM; foreign architectures (i386 ``int 0x80``,
x32) kill the process.
"""

from __future__ import annotations

import errno
import os
import tempfile

# What a child needs after it is confined: compute on memory it already has, talk over the two pipes it
# already holds (request in, result out), read clocks, and exit. Deliberately absent: open*, socket,
# connect, execve, clone/fork, kill/tkill/tgkill, pidfd_*, ptrace, process_vm_*, prctl, setrlimit/prlimit64,
# setitimer, ioctl, mount/unshare/setns, io_uring_*, bpf, userfaultfd, memfd_create.
ALLOWED_SYSCALLS: tuple[str, ...] = (
    "read", "write", "readv", "writev", "close",
    "brk", "mmap", "munmap", "mremap", "mprotect", "madvise",
    "futex", "sched_yield",
    "clock_gettime", "clock_getres", "gettimeofday", "time", "clock_nanosleep", "nanosleep",
    "getrandom",
    "rt_sigreturn", "rt_sigprocmask", "rt_sigaction", "sigaltstack",
    "getpid", "gettid", "getuid", "geteuid", "getgid", "getegid", "getrusage",
    "exit", "exit_group", "restart_syscall",
)


class PolicyUnavailable(RuntimeError):
    """The filter cannot be built here (no libseccomp, a runtime that forbids seccomp, no temporary
    directory): the sandbox must refuse to run untrusted code."""


def build_filter() -> bytes:
    """The BPF program for this machine's architecture."""
    try:
        import pyseccomp
    except (ImportError, OSError) as exc:  # pyseccomp loads libseccomp.so.2 at import time
        raise PolicyUnavailable(f"libseccomp is not available: {exc}") from exc
    try:
        rules = pyseccomp.SyscallFilter(pyseccomp.ERRNO(errno.EPERM))
        # libseccomp asks the kernel which actions it supports: a process whose own seccomp profile forbids
        # seccomp() (a container runtime's custom profile) gets EINVAL here, and must refuse, not crash
        rules.set_attr(pyseccomp.Attr.ACT_BADARCH, pyseccomp.KILL_PROCESS)
    except OSError as exc:
        raise PolicyUnavailable(f"the seccomp filter cannot be built here: {exc}") from exc
    for name in ALLOWED_SYSCALLS:
        try:
            rules.add_rule(pyseccomp.ALLOW, name)
        except (ValueError, OSError):
            continue  # not a syscall on this architecture (e.g. `time` on arm64)
    try:
        with tempfile.TemporaryFile() as out:
            rules.export_bpf(out)
            out.flush()
            os.lseek(out.fileno(), 0, os.SEEK_SET)
            return out.read()
    except OSError as exc:  # no writable temporary directory (a read-only root without a /tmp volume)
        raise PolicyUnavailable(f"the seccomp filter cannot be exported: {exc}") from exc
