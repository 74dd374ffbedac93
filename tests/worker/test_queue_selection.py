"""A worker reads the queues `PRECOND_WORKER_QUEUES` (or `precond worker --queues`) names, and no other: a training
worker reads only the training queue, trains there (in its training's own process) and never loads the code
model itself; a name that is no queue is refused naming the setting and the name. `precond prepare-model`, what a
serving pod runs before its worker, converts the model and exits."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from pydantic import ValidationError
from typer.testing import CliRunner

from precond.cli.main import app
from precond.jobs.queue.keys import QUEUES, TRAIN_QUEUE
from precond.stack.local import DEMOS, SPEC, make_stack, serving
from precond.worker.settings import WorkerSettings

pytestmark = pytest.mark.timeout(300)


def test_every_queue_by_default_and_an_unknown_name_is_refused_naming_it() -> None:
    assert WorkerSettings().queues == list(QUEUES)
    assert WorkerSettings(worker_queues=f" {TRAIN_QUEUE},{TRAIN_QUEUE}").queues == [TRAIN_QUEUE]
    with pytest.raises(ValidationError) as caught:
        WorkerSettings(worker_queues=f"{TRAIN_QUEUE},precond:queue:gpu")
    assert "PRECOND_WORKER_QUEUES" in str(caught.value) and "'precond:queue:gpu'" in str(caught.value)
    with pytest.raises(ValidationError, match="names no queue"):
        WorkerSettings(worker_queues=" , ")


def test_the_command_line_refuses_an_unknown_queue() -> None:
    result = CliRunner().invoke(app, ["worker", "--queues", "precond:queue:model,train"])
    assert result.exit_code == 2 and "--queues" in result.output and "'train'" in result.output
    assert TRAIN_QUEUE in result.output  # the names it could have used


@pytest.mark.stack
def test_a_training_worker_trains_and_never_loads_the_model(tmp_path: Path, tiny_model_dir: Path) -> None:
    # the answer waits for the whole training (a child that imports torch: more than the default 30 s on a busy
    # machine), so the 200 below is the training's result, not a 202 for a slow start
    stack = make_stack(tmp_path, tiny_model_dir, PRECOND_WORKER_QUEUES=TRAIN_QUEUE, PRECOND_WAIT_MAX_S="120")
    with serving(stack, workers=1), stack.http() as client:
        [beat] = stack.heartbeats()
        assert beat["queues"] == [TRAIN_QUEUE]
        body = {"spec": SPEC, "demonstrations": DEMOS[:2], "options": {"steps": 2, "max_tokens": 1024}}
        answer = client.post("/policies", json=body, params={"wait": 120}, timeout=150)
        assert answer.status_code == 200, answer.text
        assert answer.json()["result"]["steps"] == 2
        time.sleep(0.5)  # a heartbeat after the training
        [beat] = stack.heartbeats()
        assert beat["model_loaded"] is False


def test_prepare_model_converts_the_model_and_exits(tiny_model_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """What a serving pod's init container runs before its worker (deploy/kubernetes/base/worker.yaml)."""
    for name, value in {"MODEL_PATH": str(tiny_model_dir), "MODEL_DEVICE": "cpu", "MODEL_DTYPE": "float32",
                        "MODEL_QUANT": "none"}.items():
        monkeypatch.setenv(name, value)
    result = CliRunner().invoke(app, ["prepare-model"])
    assert result.exit_code == 0, result.output
    assert "ready: float32, quant none" in result.output
