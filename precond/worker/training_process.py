"""A policy training in a child process of the worker, so that the worker never holds the trainable model.

A training loads its own float32 copy of the model and backpropagates through it (~2.3 GB for the embedded
model); in the worker that would sit beside the served model, and glibc would keep part of it afterwards. So
the job's thread starts `python -m precond.worker.training_process` (a fresh interpreter, never a fork of a
process that holds threads and torch; it inherits the environment, so the same `MODEL_*` settings and
`MODEL_THREADS`), writes it the request and the adapter's directory on its stdin, and reads what it sends back
on its stdout, one JSON object a line: progress, then the result or the error (its type, message and field, so
that a 422 still names the field). While it waits it samples the child's resident size: above
`PRECOND_TRAINING_MAX_MEMORY_MB` the child is killed and the job fails with `resource_limit`. A cancelled job kills
the child (`Cancelled`, no adapter); a child that ends without an answer (a signal, the kernel's OOM killer, a
crash) fails the job saying how it ended. The child dies with the thread that started it (PR_SET_PDEATHSIG):
a worker that dies leaves no training running, and the queue hands the job to another worker as any other.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

from precond.jobs.lifetime import die_with_parent
from precond_client.schemas import errors
from precond_client.schemas.errors import Cancelled, PrecondError, ResourceLimit
from precond_client.schemas.training import TrainPolicyRequest, TrainPolicyResult

ProgressFn = Callable[[str, int, int], None]
PERIOD_S = 0.05
"""How often the worker checks the child's resident size and the job's cancellation while no message comes."""
EXIT_WAIT_S = 10.0
"""How long a child whose output closed without an answer may take to exit before it is killed."""
_PAGE = os.sysconf("SC_PAGE_SIZE")


class TrainingCrashed(RuntimeError):
    """The training's process ended without an answer: the service's failure, not the request's (the job fails
    as `internal`, never kept as the request's result)."""


def train(request: TrainPolicyRequest, out: Path, progress: ProgressFn, cancelled: Callable[[], bool],
          max_resident_bytes: int) -> TrainPolicyResult:
    """Train in a child process and leave the adapter at `out`; the child's errors are raised here as the
    same `PrecondError` (type, message, field). Nothing is left at `out` unless it succeeded."""
    child = subprocess.Popen([sys.executable, "-m", __name__, str(os.getpid())], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, close_fds=True)
    try:
        assert child.stdin is not None and child.stdout is not None
        with contextlib.suppress(BrokenPipeError), child.stdin:  # a child dead at once: its end says why
            child.stdin.write(json.dumps({"request": request.model_dump(mode="json"), "out": str(out)}).encode())
        for message in _messages(child, child.stdout, cancelled, max_resident_bytes):
            if "progress" in message:
                progress(*message["progress"])
            elif "error" in message:
                raise _error(message["error"])
            else:
                return TrainPolicyResult.model_validate(message["result"])
        raise TrainingCrashed(_ending(child))
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    finally:
        _end(child)


def _messages(child: subprocess.Popen[bytes], stdout: IO[bytes], cancelled: Callable[[], bool],
              max_resident_bytes: int) -> Iterator[dict[str, Any]]:
    """The child's messages until its stdout closes, checking cancellation and memory between reads."""
    fd, pending = stdout.fileno(), b""
    while True:
        if select.select([fd], [], [], PERIOD_S)[0]:
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                return
            *lines, pending = (pending + chunk).split(b"\n")
            for line in lines:
                yield json.loads(line)
        if cancelled():
            child.kill()
            raise Cancelled("the training was cancelled; no adapter was saved")
        resident = _resident(child.pid)
        if resident > max_resident_bytes:
            child.kill()
            mib = 1024 * 1024
            raise ResourceLimit(f"the training's process grew to {resident // mib:,} MiB, over "
                                f"PRECOND_TRAINING_MAX_MEMORY_MB ({max_resident_bytes // mib:,} MiB): it was stopped; "
                                "train on fewer or shorter demonstrations (options.max_tokens)")


def _resident(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/statm", "rb") as statm:
            return int(statm.read().split()[1]) * _PAGE
    except (OSError, IndexError):  # ended since the last read
        return 0


def _error(info: dict[str, Any]) -> Exception:
    kinds = {cls.kind: cls for cls in vars(errors).values()
             if isinstance(cls, type) and issubclass(cls, PrecondError)}
    if info.get("type") not in kinds:
        return TrainingCrashed(f"the training failed: {info.get('message')}")
    error: PrecondError = kinds[info["type"]](info["message"], field=info.get("field"))
    return error


def _ending(child: subprocess.Popen[bytes]) -> str:
    try:
        code = child.wait(EXIT_WAIT_S)
    except subprocess.TimeoutExpired:
        return "the training's process closed its output without an answer and did not exit; it was killed"
    if code < 0:
        name = signal.Signals(-code).name
        cause = " (the kernel's out-of-memory killer sends it)" if -code == signal.SIGKILL else ""
        return f"the training's process was killed by {name}{cause} before it answered; no adapter was saved"
    return f"the training's process exited with status {code} before it answered (its log says why); no adapter " \
           "was saved"


def _end(child: subprocess.Popen[bytes]) -> None:
    """Kill what is left of the child (it answered, or it must stop), reap it and close its output."""
    if child.poll() is None:
        child.kill()
    child.wait()
    if child.stdout is not None:
        child.stdout.close()


def _die_with_parent(parent: int) -> None:
    """The kernel kills this process when the thread that started it ends (a worker that dies); one whose parent
    is already gone exits now."""
    die_with_parent(parent)
    with contextlib.suppress(OSError), open("/proc/self/oom_score_adj", "w") as adj:
        adj.write("1000")  # under memory pressure the kernel kills the training before its worker


def _child(parent: int) -> None:
    """The child's side: read the job, train through the engine's path of loading weights, answer on the
    original stdout (everything else printed goes to stderr, the worker's log)."""
    _die_with_parent(parent)
    answers = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # before the model code is imported: nothing but `send` writes to the worker's pipe

    from precond.engine.acting.training import train_policy
    from precond.engine.factory import training_weights
    from precond.engine.spec import parse_spec

    def send(**message: Any) -> None:
        answers.write(json.dumps(message) + "\n")

    job = json.loads(sys.stdin.read())
    try:
        request = TrainPolicyRequest.model_validate(job["request"])
        result = train_policy(training_weights, parse_spec(request.spec), request, Path(job["out"]),
                              lambda stage, done, total: send(progress=[stage, done, total]), lambda: False)
    except PrecondError as exc:
        send(error={"type": exc.kind, "message": exc.message, "field": exc.field})
        return
    send(result=result.model_dump(mode="json"))


if __name__ == "__main__":
    _child(int(sys.argv[1]))
