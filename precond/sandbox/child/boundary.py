"""The isolation boundary: what the kernel enforces on a child before any untrusted byte runs.

Order matters and is the whole point of this module: the child drops every inherited descriptor, its
environment and its working directory, sets its resource limits, gives up root, and finally installs the
seccomp filter (with ``no_new_privs``). From then on the kernel refuses every system call outside the
allowlist the parent built (``sandbox.policy``): no file is opened, no socket made, no signal sent, no
process created, no limit raised, whatever the Python code does to itself. The Python-level conveniences
that follow (restricted builtins, an output cap) only make errors readable; nothing relies on them.
"""

from __future__ import annotations

import ctypes
import os
import resource
import signal
import typing

NOBODY = 65534
CLONE_NEWUSER = 0x10000000
CLONE_NEWNET = 0x40000000
PR_SET_PDEATHSIG = 1
PR_SET_DUMPABLE = 4
PR_SET_SECCOMP = 22
PR_SET_NO_NEW_PRIVS = 38
SECCOMP_MODE_FILTER = 2
BPF_INSTRUCTION_BYTES = 8
REQUEST_FD = 3
RESULT_FD = 4


class BoundaryError(Exception):
    """A protection could not be set up: the child must not run untrusted code."""


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]


_LIBC = ctypes.CDLL(None, use_errno=True)


def _prctl(option: int, arg: int, what: str) -> None:
    if _LIBC.prctl(option, arg, 0, 0, 0) != 0:
        raise BoundaryError(f"{what}: {os.strerror(ctypes.get_errno())}")


def harden_server() -> str | None:
    """The fork server (never runs untrusted code) makes itself and every child non-dumpable, so that no
    process of the same uid can open its /proc entries, and tries an empty network namespace as an extra
    layer. Returns why the namespace was not made (seccomp is the boundary, not the namespace)."""
    _prctl(PR_SET_DUMPABLE, 0, "prctl(PR_SET_DUMPABLE)")
    flags = CLONE_NEWNET if os.geteuid() == 0 else CLONE_NEWUSER | CLONE_NEWNET
    if _LIBC.unshare(flags) == 0:
        return None
    return f"unshare: {os.strerror(ctypes.get_errno())}"


def validate_filter(bpf: bytes) -> None:
    if not bpf or len(bpf) % BPF_INSTRUCTION_BYTES or len(bpf) // BPF_INSTRUCTION_BYTES > 4096:
        raise BoundaryError("seccomp filter: not a BPF program")


def confine(limits: dict[str, typing.Any], workdir: str, was_root: bool, bpf: bytes | None) -> None:
    """Everything the forked child does to itself before untrusted code runs; raises BoundaryError if any
    step fails, and the caller then exits without running anything."""
    os.setpgid(0, 0)
    devnull = os.open(os.devnull, os.O_RDWR)
    for fd in (0, 1, 2):
        os.dup2(devnull, fd)
    os.closerange(RESULT_FD + 1, 1 << 16)
    os.environ.clear()
    os.chdir(workdir)
    cpu = int(limits["cpu_s"])
    memory = int(limits["memory_mb"]) << 20
    for which, value in (
        (resource.RLIMIT_AS, memory), (resource.RLIMIT_NOFILE, int(limits["open_files"])),
        (resource.RLIMIT_NPROC, 0), (resource.RLIMIT_CORE, 0), (resource.RLIMIT_FSIZE, 0),
        (resource.RLIMIT_MEMLOCK, 0), (resource.RLIMIT_MSGQUEUE, 0),
    ):
        resource.setrlimit(which, (value, value))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 1))
    if was_root:
        os.setgroups([])
        os.setgid(NOBODY)
        os.setuid(NOBODY)
        if os.getuid() == 0 or os.geteuid() == 0:
            raise BoundaryError("could not give up root")
    _prctl(PR_SET_PDEATHSIG, signal.SIGKILL, "prctl(PR_SET_PDEATHSIG)")
    if bpf is not None:  # None only in the explicitly unconfined development mode
        install_filter(bpf)


def install_filter(bpf: bytes) -> None:
    """`no_new_privs`, then the filter; a filter can only ever be made stricter, never removed."""
    validate_filter(bpf)
    _prctl(PR_SET_NO_NEW_PRIVS, 1, "prctl(PR_SET_NO_NEW_PRIVS)")
    program = ctypes.create_string_buffer(bpf, len(bpf))
    fprog = _SockFprog(len(bpf) // BPF_INSTRUCTION_BYTES, ctypes.addressof(program))
    if _LIBC.prctl(PR_SET_SECCOMP, SECCOMP_MODE_FILTER, ctypes.byref(fprog), 0, 0) != 0:
        raise BoundaryError(f"seccomp filter: {os.strerror(ctypes.get_errno())}")
