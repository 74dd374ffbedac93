"""The queue's records (precond/jobs/queue/payloads.py): what gateway and worker write is what the published JSON
Schema (openapi/queue-records.schema.json) describes, and bytes that are not a record of this version (a pickle
above all: the queue Redis is writable by more than this code) are refused unread, as root and as a non-root user,
naming what is wrong."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from precond.jobs.queue.payloads import (
    RECORD_VERSION,
    EndRecord,
    Outcome,
    RecordError,
    cancelled_end,
    decode_end,
    decode_job,
    decode_progress,
    encode_end,
    encode_job,
    encode_progress,
)
from precond_client.schemas import JobProgress

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = json.loads((ROOT / "openapi" / "queue-records.schema.json").read_text())

PICKLE_PROBE = """
import pickle, sys
from precond.jobs.queue import payloads

class Planted:
    def __reduce__(self):
        return (open, (sys.argv[1], "w"))

raw = pickle.dumps(Planted())
refused = []
for name in ("decode_job", "decode_end"):
    try:
        getattr(payloads, name)(raw)
    except Exception as exc:
        refused.append(type(exc).__name__)
print(" ".join(refused))
"""


@pytest.mark.parametrize("user", ["root", "nobody"])
def test_a_pickle_where_a_record_belongs_runs_nothing_as_root_or_not(user: str, tmp_path: Path) -> None:
    if user == "nobody" and os.geteuid() != 0:
        pytest.skip("already not root: the root case ran as this user")
    tmp_path.chmod(0o777)
    canary = tmp_path / "pwned"
    prefix = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"] if user == "nobody" else []
    done = subprocess.run([*prefix, sys.executable, "-c", PICKLE_PROBE, str(canary)], cwd=tmp_path,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, capture_output=True, text=True,
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert not canary.exists(), "a pickle from Redis was run"
    assert done.stdout.split() == ["RecordError", "RecordError"]


def validate(raw: bytes | str, name: str) -> None:
    jsonschema.validate(json.loads(raw), {**SCHEMA, "$ref": f"#/$defs/{name}"})


def test_what_gateway_and_worker_write_is_what_the_schema_describes() -> None:
    job = encode_job("check", {"spec": "x", "calls": ["a()"]}, "check-shared-00", 1_700_000_000_000)
    validate(job, "JobRecord")
    assert decode_job(job).body == {"spec": "x", "calls": ["a()"]}
    progress = encode_progress(JobProgress(phase="checking", done=1, total=2))
    validate(progress, "ProgressRecord")
    assert decode_progress(progress.encode()) == JobProgress(phase="checking", done=1, total=2)
    end = EndRecord(version=RECORD_VERSION, job_id="j", queue="q", job_try=1, enqueued_ms=1, start_ms=2, finish_ms=3,
                    outcome=Outcome(status="succeeded", result={"results": []}))
    validate(encode_end(end), "EndRecord")
    assert decode_end(encode_end(end)) == end
    validate(cancelled_end("j", "q", 5), "EndRecord")


@pytest.mark.parametrize(("record", "problem"), [
    ({"version": 2, "kind": "check", "body": {}, "cache_key": "c", "enqueued_ms": 1}, "version"),
    ({"kind": "check", "body": {}, "cache_key": "c", "enqueued_ms": 1}, "version: Field required"),
    ({"version": 1, "kind": "eval", "body": {}, "cache_key": "c", "enqueued_ms": 1}, "kind"),
    ({"version": 1, "kind": "check", "body": [], "cache_key": "c", "enqueued_ms": 1}, "body"),
    ({"version": 1, "kind": "check", "body": {}, "cache_key": "c", "enqueued_ms": 1, "args": []}, "args"),
])
def test_a_job_record_that_fails_its_schema_is_refused_naming_the_field(record: dict[str, Any], problem: str
                                                                        ) -> None:
    with pytest.raises(RecordError, match=f"not a version-1 JobRecord: .*{problem}"):
        decode_job(json.dumps(record).encode())


def test_an_end_with_neither_or_both_outcome_and_failure_is_refused() -> None:
    base = {"version": 1, "job_id": "j", "queue": "q", "job_try": 1, "enqueued_ms": 1, "start_ms": 1, "finish_ms": 1}
    for extra in ({}, {"outcome": {"status": "succeeded"}, "failure": {"reason": "crashed", "message": "x"}}):
        with pytest.raises(RecordError, match="exactly one"):
            decode_end(json.dumps({**base, **extra}).encode())


def test_progress_that_is_not_a_record_reads_as_none_yet() -> None:
    """Progress is advisory: the job's end, read with it, says what went wrong."""
    assert decode_progress(b"\x80\x05N.") == JobProgress() == decode_progress(None)
