"""A worker told to stop (SIGTERM) while it still loads its model stops within its drain, without waiting for the
load: a load cannot be interrupted, and one read from a slow disk takes tens of seconds."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from precond.stack.local import ROOT, make_stack, serving, wait_until

pytestmark = [pytest.mark.timeout(300), pytest.mark.stack]

SLOW_LOAD = """\
import time
from pathlib import Path

if b"precond.worker.runner" in Path("/proc/self/cmdline").read_bytes().split(b"\\0"):
    import precond.engine.models as models

    def load_code_model(*args, **kwargs):
        Path({started!r}).touch()
        time.sleep(600)  # a load that outlasts the test

    models.load_code_model = load_code_model
"""


def test_a_worker_stopped_while_its_model_loads_exits_without_waiting_for_the_load(
    tmp_path: Path, tiny_model_dir: Path
) -> None:
    slow, started = tmp_path / "slow-load", tmp_path / "load-started"
    slow.mkdir()
    (slow / "sitecustomize.py").write_text(SLOW_LOAD.format(started=str(started)))
    stack = make_stack(tmp_path, tiny_model_dir, PYTHONPATH=f"{slow}:{ROOT}")
    with serving(stack):
        worker = stack.start_worker()
        wait_until(started.exists, 60, "the model's load to start")
        worker.send_signal(signal.SIGTERM)
        assert worker.wait(60) == 0  # the drain is 1 s (PRECOND_DRAIN_S); the load would take 600
        assert stack.heartbeats() == []  # it said goodbye: no heartbeat is left to expire
