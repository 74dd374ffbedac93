"""Several gateway processes behind one port (`PRECOND_GATEWAY_PROCESSES`): each serves, none loses a job."""

from __future__ import annotations

from pathlib import Path

import pytest

from precond.stack.local import check_body, make_stack, serving

pytestmark = pytest.mark.stack


def test_two_gateway_processes_share_the_port_and_the_jobs(tmp_path: Path, tiny_model_dir: Path) -> None:
    stack = make_stack(tmp_path, tiny_model_dir, PRECOND_GATEWAY_PROCESSES="2")
    with serving(stack, workers=1):
        manager = stack.processes[0].pid
        children = Path(f"/proc/{manager}/task/{manager}/children").read_text().split()
        assert len(children) >= 2  # uvicorn's manager and its two serving processes
        for i in range(12):  # a new connection each: the kernel spreads them over both processes
            with stack.http(timeout=60) as client:
                answer = client.post("/check-actions", json=check_body(f"system.REQUEST('slot_{i}')"),
                                     params={"wait": 30})
            assert answer.status_code == 200, answer.text
            assert answer.json()["results"][0]["allowed"] is True
