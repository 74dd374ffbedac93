"""What a check's queue records cost to write and read: arq's pickled job and result records (what the queue
stored before its records were its own) against the JSON records of precond/jobs/queue/payloads.py, validated
by their versioned models on the way in.

    python bench/queue_records_bench.py [--repeat 20000] [--rounds 7] [--json out.json]

One check's records, as a check's round trip writes and reads them: the job (the body of
examples/check-actions.json) encoded by the gateway and decoded by the worker, and its end (a check's answer)
encoded by the worker and decoded by the gateway. The two codecs alternate, `--rounds` times `--repeat` round
trips each, and the figure is each codec's median per round trip (process CPU time): paired, so that a machine
shared with other work slows both alike.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from arq.jobs import deserialize_job_raw, deserialize_result, serialize_job, serialize_result  # noqa: E402

from precond.jobs.queue.payloads import (  # noqa: E402
    RECORD_VERSION,
    EndRecord,
    Outcome,
    decode_end,
    decode_job,
    encode_end,
    encode_job,
)

JOB_ID = "check-0123456789abcdef-" + "0" * 48
QUEUE = "precond:queue:check"


def check_answer(body: dict[str, Any]) -> dict[str, Any]:
    """A check's answer as the worker returns it: one verdict per call, with the rule that decided it."""
    return {"results": [{"call": call, "allowed": True, "violations": [], "unknown": []} for call in body["calls"]],
            "set": None}


def pickled(body: dict[str, Any], answer: dict[str, Any]) -> None:
    raw = serialize_job("run_operation", ("check", body, JOB_ID), {}, None, 1)
    _, args, _, _, enqueued = deserialize_job_raw(raw)
    end = serialize_result("run_operation", args, {}, 1, enqueued, True, answer, 2, 3, f"{JOB_ID}:run_operation",
                           QUEUE, JOB_ID)
    assert end is not None
    deserialize_result(end)


def as_json(body: dict[str, Any], answer: dict[str, Any]) -> None:
    record = decode_job(encode_job("check", body, JOB_ID, 1))
    end = encode_end(EndRecord.model_construct(version=RECORD_VERSION, job_id=JOB_ID, queue=QUEUE, job_try=1,
                               enqueued_ms=record.enqueued_ms, start_ms=2, finish_ms=3,
                               outcome=Outcome(status="succeeded", result=answer)))
    decode_end(end)


def per_round_trip_us(codec: Callable[[dict[str, Any], dict[str, Any]], None], body: dict[str, Any],
                      answer: dict[str, Any], repeat: int) -> float:
    started = time.process_time()
    for _ in range(repeat):
        codec(body, answer)
    return (time.process_time() - started) / repeat * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=20000)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    body = json.loads((ROOT / "examples" / "check-actions.json").read_text())
    answer = check_answer(body)
    times: dict[str, list[float]] = {"pickle": [], "json": []}
    for _ in range(args.rounds):
        times["pickle"].append(per_round_trip_us(pickled, body, answer, args.repeat))
        times["json"].append(per_round_trip_us(as_json, body, answer, args.repeat))
    report = {
        "machine": platform.processor() or platform.machine(),
        "repeat": args.repeat,
        "rounds": args.rounds,
        "job_bytes": {"pickle": len(serialize_job("run_operation", ("check", body, JOB_ID), {}, None, 1)),
                      "json": len(encode_job("check", body, JOB_ID, 1))},
        "us_per_check_round_trip": {name: round(statistics.median(values), 2) for name, values in times.items()},
    }
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
