"""Run inside a mount namespace whose root filesystem is read-only (test_read_only_root.py): a stack as the
pods run it, where the worker may write only under /tmp (standing for its /tmp and /models volumes) and the
gateway nowhere at all (its own namespace makes /tmp read-only too); /dev/shm stays the runtime's tmpfs.
Sends a check, a long check the gateway parses in its check processes, an enumerate-only inference and a
model inference, and prints their outcomes as JSON."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from precond.gateway.server import gateway_args
from precond.stack.local import check_body, example, infer_body, make_stack, wait_until

READ_ONLY_TMP = ["unshare", "--mount", "--propagation", "private", "sh", "-c",
                 'mount -o remount,bind,ro /tmp && exec "$@"', "read-only-tmp"]


def outcome(http: httpx.Client, path: str, body: dict[str, Any]) -> str:
    answer = http.post(path, json=body, params={"wait": 0})
    job = answer.headers.get("X-Job-Id")
    if answer.status_code != 202 or job is None:
        return f"http {answer.status_code}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        status = str(http.get(f"/jobs/{job}").json()["status"])
        if status in ("succeeded", "failed", "cancelled"):
            return status
        time.sleep(0.1)
    return "timed out"


def main(tmp: Path, model_dir: Path) -> dict[str, str]:
    stack = make_stack(tmp, model_dir, MODEL_CACHE_DIR=str(tmp / "models"), PRECOND_MAX_BODY_BYTES="1048576",
                       PRECOND_PRELOAD_MODEL="true")
    try:
        stack._spawn("gateway", [*READ_ONLY_TMP, sys.executable, "-m", "uvicorn", *gateway_args(1),
                                 "--port", str(stack.port), "--log-level", "warning"])
        wait_until(lambda: stack.http().get("/health").status_code == 200, 60, "gateway")
        stack._spawn("worker", [sys.executable, "-m", "precond.worker.runner"])
        wait_until(lambda: stack.http().get("/ready").status_code == 200, 120, "a ready worker")
        long_check = check_body()
        long_check["history"] += "# " + "x" * 20_000 + "\n"  # over the gateway's inline size: a check process
        model = example("infer-model")
        model["options"].update(samples_per_prompt=1, prompts_per_action=1, max_new_tokens=8)
        with stack.http(timeout=120) as http:
            return {"check": outcome(http, "/check-actions", check_body()),
                    "long check": outcome(http, "/check-actions", long_check),
                    "enumerate": outcome(http, "/infer-preconditions", infer_body(seed=7)),
                    "model": outcome(http, "/infer-preconditions", model)}
    finally:
        stack.stop()
        stack.redis.stop()


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]), Path(sys.argv[2]))))
