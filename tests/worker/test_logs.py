"""The worker's log says each thing once: one process serves every queue, and logs its start in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from precond.stack.local import RedisServer

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.stack
def test_a_worker_process_logs_its_start_once(tmp_path: Path) -> None:
    redis = RedisServer(tmp_path)
    redis.start()
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "REDIS_URL": redis.url, "PRECOND_SECRET": "x" * 32,
           "OMP_NUM_THREADS": "1", "PRECOND_PRELOAD_MODEL": "false"}
    code = ("import threading, os, signal; from precond.worker.runner import run; from precond.worker.settings import "
            "get_worker_settings; threading.Timer(4, lambda: os.kill(os.getpid(), signal.SIGTERM)).start(); "
            "run(get_worker_settings())")
    try:
        out = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True,
                             timeout=120)
    finally:
        redis.stop()
    starts = [line for line in out.stderr.splitlines() if " started: queues " in line]
    assert len(starts) == 1, out.stderr[-3000:]
