"""Behaviour cloning's cost: `precond train-policy` with its defaults on one SGD dev domain's ten
demonstrations, in a fresh process (so the peak resident memory is the training's), with every core
(`MODEL_THREADS`, default: all). The bound: at most 5 minutes per domain on the 2-core machine, an
adapter of at most 20 MB.

    python bench/train_policy_bench.py [--domain Buses_1] [--steps 24] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import tempfile
import time
from pathlib import Path

from precond.engine.acting.training import train_policy
from precond.engine.models.weights import load_weights
from precond.engine.settings import ModelSettings
from precond.engine.spec import parse_spec
from precond.evaluation.domains import load_sgd
from precond.evaluation.report import cpu_model
from precond.evaluation.settings import DataSettings
from precond_client.schemas.training import TrainPolicyOptions, TrainPolicyRequest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--domain", default="Buses_1")
    parser.add_argument("--steps", type=int, default=TrainPolicyOptions().steps)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    domain = load_sgd(DataSettings().path("sgd") / f"{args.domain}.json")
    threads = int(os.environ.get("MODEL_THREADS", os.cpu_count() or 1))
    request = TrainPolicyRequest(spec=domain.spec, demonstrations=list(domain.demonstrations),
                                 options=TrainPolicyOptions(steps=args.steps))
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        result = train_policy(lambda: load_weights(ModelSettings(threads=threads)), parse_spec(request.spec), request,
                              Path(scratch) / "bc", lambda *_: None, lambda: False)
    wall = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    row = {"domain": args.domain, "cpu": cpu_model(), "threads": threads, "steps": result.steps,
           "training_s": result.seconds, "wall_s": round(wall, 1), "peak_rss_mb": round(peak_mb),
           "adapter_mb": round(result.adapter_bytes / 1e6, 2), "first_loss": result.losses[0],
           "last_loss": result.losses[-1], "dtype": result.dtype}
    print(json.dumps(row, indent=1))
    if args.json:
        args.json.write_text(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
