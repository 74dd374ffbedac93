"""A serving worker whose memory limit cannot hold its model refuses to load it, before reading a weight, and says
why (its heartbeat's `model_error`, the gateways' /ready) instead of running while the kernel evicts its weights
or kills it; it stays up and runs what needs no model."""

from __future__ import annotations

from pathlib import Path

import pytest

from precond.stack.local import ROOT, check_body, make_stack, serving, wait_until

pytestmark = [pytest.mark.timeout(300), pytest.mark.stack]

LIMIT = """\
from pathlib import Path

if b"precond.worker.runner" in Path("/proc/self/cmdline").read_bytes().split(b"\\0"):
    from precond.engine.models import memory_fit

    memory_fit.memory_limit = lambda: memory_fit.MemoryLimit(64 << 20, Path("/sys/fs/cgroup/memory.max"))
"""


def test_a_worker_whose_limit_cannot_hold_the_model_says_why_and_runs_checks(
    tmp_path: Path, tiny_model_dir: Path
) -> None:
    small = tmp_path / "small-limit"
    small.mkdir()
    (small / "sitecustomize.py").write_text(LIMIT)  # the worker's limit reader answers 64 MiB
    stack = make_stack(
        tmp_path, tiny_model_dir, PYTHONPATH=f"{small}:{ROOT}", MODEL_DTYPE="float32", MODEL_QUANT="none"
    )
    with serving(stack, workers=1), stack.http() as client:
        wait_until(lambda: stack.heartbeats()[0].get("model_error"), 60, "the refused load")
        [beat] = stack.heartbeats()
        error, pid = str(beat["model_error"]), beat["pid"]
        assert beat["model_loaded"] is False
        for part in (
            "ModelTooLarge",
            "float32 (MODEL_DTYPE=float32: float32)",
            "quant none (MODEL_QUANT=none)",
            "over the limit of 64 MiB (/sys/fs/cgroup/memory.max)",
            "PRECOND_WORKER_MEMORY",
        ):
            assert part in error, (part, error)
        ready = client.get("/ready")
        assert ready.status_code == 503 and "memory limit" in ready.text and "64 MiB" in ready.text, ready.text
        checked = client.post("/check-actions", json=check_body(), params={"wait": 30})
        assert checked.status_code == 200, checked.text
        assert [b["pid"] for b in stack.heartbeats()] == [pid]  # the same worker, up all along
