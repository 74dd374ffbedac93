"""A worker's policy training runs in a child process (precond/worker/training_process.py), never in the worker:
its adapter and result come back, its errors keep their type and field, and a cancellation, the memory bound or
a signal ends the child with the job's error and leaves neither a process nor an adapter behind. The tiny
random model stands in for the real one."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from precond.engine.models.adapters import read_result
from precond.worker.training_process import TrainingCrashed, train
from precond_client.schemas.errors import Cancelled, InvalidInput, ResourceLimit
from tests.models.test_policy_training import _request

pytestmark = [pytest.mark.timeout(300), pytest.mark.long]  # long: collected first, started first
GIB = 1024**3


@pytest.fixture(autouse=True)
def tiny_model(tiny_model_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The child reads the model's settings from the environment it inherits, as a worker's does."""
    for name, value in {"MODEL_PATH": str(tiny_model_dir), "MODEL_DEVICE": "cpu", "MODEL_DTYPE": "float32",
                        "MODEL_QUANT": "none", "MODEL_THREADS": "1"}.items():
        monkeypatch.setenv(name, value)


def children() -> set[int]:
    """This process's child processes (read from /proc: no CONFIG_PROC_CHILDREN needed)."""
    found = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == os.getpid():
                found.add(int(entry.name))
    return found


class Watch:
    """A progress callback that notes the child processes alive at each report, and may act at the first report
    of the training's steps."""

    def __init__(self, at_train: Callable[[set[int]], None] = lambda _: None) -> None:
        self.reports: list[tuple[str, int, int]] = []
        self.seen: set[int] = set()
        self.at_train = at_train
        self.before = children()

    def __call__(self, stage: str, done: int, total: int) -> None:
        new = children() - self.before
        self.seen |= new
        if stage == "train" and not any(s == "train" for s, _, _ in self.reports):
            self.at_train(new)
        self.reports.append((stage, done, total))


def gone(pids: set[int]) -> bool:
    deadline = time.monotonic() + 5
    while pids & children() and time.monotonic() < deadline:
        time.sleep(0.05)
    return not pids & children()


def test_the_training_runs_in_a_child_and_leaves_its_adapter(tmp_path: Path) -> None:
    watch = Watch()
    result = train(_request(steps=3), tmp_path / "bc", watch, lambda: False, 4 * GIB)
    assert read_result(tmp_path / "bc") == result and result.steps == 3 and result.adapter_bytes > 0
    assert ("train", 3, 3) in watch.reports and ("train", 0, 3) in watch.reports
    assert len(watch.seen) == 1 and os.getpid() not in watch.seen  # trained in one other process
    assert gone(watch.seen)


def test_an_error_in_the_child_comes_back_with_its_type_and_field(tmp_path: Path) -> None:
    with pytest.raises(InvalidInput) as caught:
        train(_request(max_tokens=64), tmp_path / "bc", Watch(), lambda: False, 4 * GIB)
    assert caught.value.field == "options.max_tokens" and "beyond options.max_tokens" in caught.value.message
    assert not (tmp_path / "bc").exists()


def test_a_cancelled_training_kills_its_child_and_saves_nothing(tmp_path: Path) -> None:
    stop: list[bool] = []
    watch = Watch(lambda _: stop.append(True))
    with pytest.raises(Cancelled):
        train(_request(steps=300), tmp_path / "bc", watch, lambda: bool(stop), 4 * GIB)
    assert watch.seen and gone(watch.seen)
    assert watch.reports[-1][1] < 300 and not (tmp_path / "bc").exists()


def test_a_child_over_the_memory_bound_is_killed_naming_the_setting(tmp_path: Path) -> None:
    before = children()
    started = time.monotonic()
    with pytest.raises(ResourceLimit) as caught:
        train(_request(steps=3), tmp_path / "bc", Watch(), lambda: False, 64 * 1024 * 1024)
    assert "PRECOND_TRAINING_MAX_MEMORY_MB" in caught.value.message
    assert time.monotonic() - started < 60 and children() <= before
    assert not (tmp_path / "bc").exists()


def test_a_child_killed_by_a_signal_fails_the_job_saying_so(tmp_path: Path) -> None:
    def kill(pids: set[int]) -> None:
        for pid in pids:
            os.kill(pid, signal.SIGKILL)

    watch = Watch(kill)
    with pytest.raises(TrainingCrashed, match="killed by SIGKILL"):
        train(_request(steps=300), tmp_path / "bc", watch, lambda: False, 4 * GIB)
    assert watch.seen and gone(watch.seen) and not (tmp_path / "bc").exists()
