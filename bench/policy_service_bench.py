"""A trained policy through the service, on loopback (own redis-server, uvicorn gateway, one `precond worker`):

    python bench/policy_service_bench.py [--model embedded] [--domain Events_1] [--steps 24] [--asks 8]
        [--env MODEL_THREADS=2] [--json out.json]

One tenant (`quiet`) trains a policy on the domain's ten dev demonstrations (`POST /policies`, a job on the
training queue) while the other (`flood`) asks for next actions with the base model: their latency during the
training and after it shows whether a training holds the model queue (it has its own queue and slot, so it
should only share the CPU). Then `quiet` asks for next actions with its policy (`options.policy`): latency of
the first (the worker builds the adapted model) and of the rest, and the worker's resident memory before and
after (the adapted copy of the attention projections).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.service_bench import auth, make_keys, stack  # noqa: E402
from precond.evaluation.domains import load_sgd  # noqa: E402
from precond.evaluation.report import cpu_model  # noqa: E402
from precond.evaluation.settings import DataSettings  # noqa: E402


def worker_rss_mb() -> float:
    """Resident memory of the `precond worker` process (the one whose command line runs the CLI's worker)."""
    for proc in Path("/proc").iterdir():
        try:
            cmdline = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"worker" in cmdline and any(b"app()" in part for part in cmdline):
            status = (proc / "status").read_text()
            return int(status.split("VmRSS:")[1].split()[0]) / 1024
    raise SystemExit("no worker process found")


def asks(domain: Any, count: int, policy: str | None, first_seed: int) -> list[dict[str, Any]]:
    """Next-action requests, each a new job (its own seed): the spec, no demonstrations, no rules, and the
    first third of a test dialog."""
    bodies = []
    for i, program in enumerate(domain.test[:count]):
        lines = program.splitlines(keepends=True)
        history = "".join(lines[: max(3, len(lines) // 3)])
        options: dict[str, Any] = {"seed": first_seed + i}
        if policy:
            options["policy"] = policy
        bodies.append({"spec": domain.spec, "history": history, "options": options})
    return bodies


def timed(client: httpx.Client, body: dict[str, Any]) -> float:
    started = time.perf_counter()
    answer = client.post("/next-action", json=body, params={"wait": 600}, timeout=700)
    if answer.status_code == 202:  # the gateway caps `wait`: a loaded machine outlasts it
        job = answer.json()["id"]
        while (answer := client.get(f"/jobs/{job}")).json()["status"] in ("queued", "running"):
            time.sleep(0.05)
        if answer.json()["status"] != "succeeded":
            raise SystemExit(f"/next-action: {answer.text[:300]}")
    elif answer.status_code != 200:
        raise SystemExit(f"/next-action: {answer.status_code} {answer.text[:300]}")
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="embedded")
    parser.add_argument("--domain", default="Events_1")
    parser.add_argument("--steps", type=int, default=24)
    parser.add_argument("--asks", type=int, default=8)
    parser.add_argument("--env", action="append", default=[], metavar="K=V")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    domain = load_sgd(DataSettings().path("sgd") / f"{args.domain}.json")
    row: dict[str, Any] = {"cpu": cpu_model(), "domain": args.domain, "steps": args.steps, "model": args.model}
    with tempfile.TemporaryDirectory() as scratch:
        tmp = Path(scratch)
        keys = make_keys(tmp / "keys.jsonl")
        ns = argparse.Namespace(root=ROOT, model=args.model, gateway_processes=1, env=args.env, flood=0)
        with stack(ns, tmp) as base, httpx.Client(base_url=base, headers=auth(keys["quiet"])) as quiet, \
                httpx.Client(base_url=base, headers=auth(keys["flood"])) as flood:
            row["base_alone_s"] = [round(timed(flood, b), 2) for b in asks(domain, 2, None, 0)]
            body = {"spec": domain.spec, "demonstrations": list(domain.demonstrations),
                    "options": {"steps": args.steps}}
            started = time.perf_counter()
            job = quiet.post("/policies", json=body, params={"wait": 0})
            if job.status_code != 202:
                raise SystemExit(f"/policies: {job.status_code} {job.text[:300]}")
            beside: list[float] = []
            done = threading.Event()

            def ask_beside() -> None:
                for b in asks(domain, 50, None, 100):
                    if done.is_set():
                        return
                    beside.append(timed(flood, b))

            asker = threading.Thread(target=ask_beside)
            asker.start()
            while (status := quiet.get(f"/jobs/{job.json()['id']}").json())["status"] in ("queued", "running"):
                time.sleep(2)
            row["training_wall_s"] = round(time.perf_counter() - started, 1)
            done.set()
            asker.join()
            if status["status"] != "succeeded":
                raise SystemExit(f"training {status['status']}: {status.get('error')}")
            policy = status["result"]
            trained = policy["result"]
            row.update(training_s=trained["seconds"], adapter_mb=round(trained["adapter_bytes"] / 1e6, 2),
                       first_loss=trained["losses"][0], last_loss=trained["losses"][-1],
                       base_beside_training_s=[round(s, 2) for s in beside])
            row["worker_rss_before_mb"] = round(worker_rss_mb())
            tuned = [timed(quiet, b) for b in asks(domain, args.asks, f"adapter:{policy['id']}", 300)]
            row["worker_rss_after_mb"] = round(worker_rss_mb())
            row["policy_first_s"] = round(tuned[0], 2)
            rest = sorted(tuned[1:])
            row["policy_rest_median_s"] = round(statistics.median(rest), 2) if rest else None
            row["policy_rest_p95_s"] = round(rest[min(len(rest) - 1, round(0.95 * (len(rest) - 1)))], 2) \
                if rest else None
            row["policy_rest_s"] = [round(s, 2) for s in tuned[1:]]
            row["base_after_s"] = [round(timed(flood, b), 2) for b in asks(domain, 2, None, 200)]
    print(json.dumps(row, indent=1))
    if args.json:
        args.json.write_text(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
