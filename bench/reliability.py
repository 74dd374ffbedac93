"""Reliability scenarios at full size (docs/reliability.md); tests/reliability/ runs the same code small.

    python bench/reliability.py                          # every scenario, full size (~15 min on 2 cores)
    python bench/reliability.py crash redis              # some of them
    python bench/reliability.py --quick                  # the CI sizes
    python bench/reliability.py --json bench/reliability.json
    python bench/reliability.py attacks --attack 8-tool-calls    # the unloaded phase and one attack

Scenarios: crash (200 infer jobs, a worker SIGKILLed 6 times, then
the same without kills), redis (SIGTERM and SIGKILL restart with the
append-only file), hostile (the hostile corpus over HTTP, production sandbox limits), fuzz (schemathesis,
all operations), overload (48 clients on one worker, queue bound 8), shutdown (SIGTERM mid-job, drain longer
and shorter than the job), attacks (one tenant runs each attack of docs/security.md while another measures its uncached
check-actions and enumerate-only inference latencies, /health, the gateway's resident size and worker
deaths: precond/stack/attacks.py; attack 8 is 24 concurrent tool-call checks of a 62 KB spec). Each runs on
its own redis-server + gateway + workers on free loopback ports, with the tiny random model of
precond/stack/tiny_model.py (model-free enumerate jobs do the real work).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from precond.stack import attacks, scenarios  # noqa: E402
from precond.stack.harness import FAST_SANDBOX, scenario_stack  # noqa: E402
from precond.stack.keyed import keyed_stack  # noqa: E402
from precond.stack.local import wait_until  # noqa: E402
from precond.stack.tiny_model import build_tiny_model  # noqa: E402

FULL: dict[str, dict[str, Any]] = {
    "crash": {"jobs": 200, "kills": 6, "millions": 5},
    "redis": {"jobs": 40, "millions": 5, "down_s": 5.0},
    "fuzz": {"max_examples": 100},
    "overload": {"clients": 48, "duration_s": 60.0, "millions": 5},
    "shutdown": {"millions": 90},
    "attacks": {"duration_s": 30.0},
}
QUICK: dict[str, dict[str, Any]] = {
    "crash": {"jobs": 40, "kills": 3, "millions": 3},
    "redis": {"jobs": 12, "millions": 3, "down_s": 2.0},
    "fuzz": {"max_examples": 15},
    "overload": {"clients": 24, "duration_s": 12.0, "millions": 3},
    "shutdown": {"millions": 90},
    "attacks": {"duration_s": 10.0},
}


def run(name: str, size: dict[str, Any], tmp: Path, model: Path, quick: bool, chosen: list[str] | None) -> Any:
    sandbox = FAST_SANDBOX if quick else {}
    where = tmp / name
    where.mkdir()
    if name == "crash":
        with scenario_stack("crash", where, model) as stack:
            figures = {"with_kills": scenarios.worker_crashes(stack, **size)}
        if not quick:  # the same load without kills: the extra latency is the difference
            (where / "baseline").mkdir()
            with scenario_stack("crash", where / "baseline", model) as stack:
                figures["baseline"] = scenarios.worker_crashes(stack, **{**size, "kills": 0})
        return figures
    if name == "redis":
        restarts: list[Any] = []
        for kill in (False, True):
            sub = where / ("kill" if kill else "term")
            sub.mkdir()
            with scenario_stack("redis", sub, model, persistent=True) as stack:
                restarts.append(scenarios.redis_restart(stack, kill=kill, **size))
        return restarts
    if name == "hostile":
        canaries = where / "canaries"
        canaries.mkdir()
        with scenario_stack("hostile", where, model, False, **sandbox) as stack:
            return scenarios.hostile_input(stack, canaries)
    if name == "fuzz":
        with scenario_stack("fuzz", where, model, False, **FAST_SANDBOX) as stack:
            return scenarios.fuzz(stack, seed=1, out=where / "schemathesis", **size)
    if name == "overload":
        with scenario_stack("overload", where, model) as stack:
            return scenarios.overload(stack, **size)
    if name == "shutdown":
        shutdowns: list[Any] = []
        for covers in (True, False):
            sub = where / ("drain" if covers else "handback")
            sub.mkdir()
            with scenario_stack("shutdown-drain" if covers else "shutdown-handback", sub, model) as stack:
                shutdowns.append(scenarios.graceful_shutdown(stack, drain_covers_job=covers, **size))
        return shutdowns
    if name == "attacks":
        settings = {"PRECOND_MAX_BODY_BYTES": "4194304", "SANDBOX_TIMEOUT_S": "10", "SANDBOX_CPU_S": "10"}
        with keyed_stack(where, model, ("victim", "attacker"), workers=1, **settings) as keyed:
            with keyed.stack.http() as http:
                wait_until(lambda: http.get("/ready").status_code == 200, 120, "the worker's model to load")
            return attacks.tenant_attacks(keyed, **size, names=chosen)
    raise SystemExit(f"unknown scenario {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("names", nargs="*",
                        default=["crash", "redis", "hostile", "fuzz", "overload", "shutdown", "attacks"])
    parser.add_argument("--quick", action="store_true", help="the CI sizes (and CI's short sandbox limits)")
    parser.add_argument("--json", type=Path, help="write all figures here")
    parser.add_argument("--keep", action="store_true", help="keep the temp dir (logs, schemathesis reports)")
    parser.add_argument("--attack", action="append", choices=sorted(attacks.ATTACKS),
                        help="with `attacks`: only this one (repeatable; default: every attack)")
    args = parser.parse_args()
    sizes = QUICK if args.quick else FULL
    tmp = Path(tempfile.mkdtemp(prefix="reliability-"))
    model = build_tiny_model(tmp / "tiny-model")
    figures: dict[str, Any] = {}
    for name in args.names:
        figures[name] = run(name, sizes.get(name, {}), tmp, model, args.quick, args.attack)
        shown = figures[name]
        if name == "hostile":
            shown = {k: v for k, v in shown.items() if k != "results"}
        print(f"== {name}\n{json.dumps(shown, indent=2)}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    print(f"logs and reports: {tmp}")


if __name__ == "__main__":
    main()
