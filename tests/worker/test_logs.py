"""The worker's log says each thing once: its three arq workers (one per queue) log start and stop alike."""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from pathlib import Path

from precond.stack.local import RedisServer
from precond.worker.logs import Deduplicated

ROOT = Path(__file__).resolve().parents[2]


def _record(message: str) -> logging.LogRecord:
    return logging.LogRecord("arq.worker", logging.INFO, __file__, 1, message, None, None)


def test_identical_lines_are_kept_once_and_different_ones_all() -> None:
    keep = Deduplicated(window_s=60).filter
    assert [keep(_record("Starting worker for 1 functions: run_operation")) for _ in range(3)] == [True, False, False]
    assert [keep(_record(f"redis_version=7.0.15 mem_usage=1.{n}M clients_connected={n} db_keys=1"))
            for n in (17, 20, 21)] == [True, False, False]
    assert keep(_record("shutdown on SIGTERM ◆ 3 jobs complete")) and keep(_record("shutdown on SIGTERM ◆ 9 jobs "
                                                                                      "complete"))
    assert keep(_record("  0.12s → abc:run_operation()")) and keep(_record("  0.13s → def:run_operation()"))


def test_a_line_is_logged_again_after_the_window() -> None:
    keep = Deduplicated(window_s=0.05).filter
    assert keep(_record("Starting worker for 1 functions: run_operation"))
    time.sleep(0.1)
    assert keep(_record("Starting worker for 1 functions: run_operation"))  # a restart after an outage


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
    starts = [line for line in out.stderr.splitlines() if "Starting worker for" in line]
    assert len(starts) == 1, out.stderr[-3000:]
