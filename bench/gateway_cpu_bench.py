"""The gateway's CPU time per request: a cache hit, and an uncached check the gateway judges itself.

Requests per second on a shared 2-core machine say as much about the other work on it as about the gateway;
the CPU the gateway's processes spent over a known number of requests does not (contention stretches the wall
time, not the work). For each checkout (`--root`, repeat to compare) a stack is started as in
`service_bench.py` (API keys on, `--gateway-processes` processes behind the port); then, `--rounds` times, each
checkout in turn (the order rotated), `wrk -t2 -c32` for `--seconds` of each row:

  * cache hit: one check-actions body that takes the queue, answered from the result cache after its first run;
  * interpreter: check-actions of the example (an SGD spec, rules the interpreter evaluates), a new call in
    every request, so no cache holds it (`judged_by: "interpreter"`).

CPU is the user and system time (/proc, through psutil) of every process under the uvicorn supervisor (the
gateway processes and their check pools) and of the supervisor, read before and after each wrk run; divided by
the requests wrk completed. Every answer must be 200 (wrk's non-2xx count ends the run).

    python bench/gateway_cpu_bench.py --root OLD_CHECKOUT --root . --rounds 3 --seconds 4
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))

from service_bench import CALL, EXAMPLES, ROOT, WRK_LUA, WRK_SEQUENTIAL_LUA, sandboxed, start, timed_post


def gateway_processes(base: str) -> list[psutil.Process]:
    """The uvicorn supervisor listening on `base`'s port and everything under it."""
    port = base.rsplit(":", 1)[1]
    for process in psutil.process_iter(["cmdline"]):
        argv = process.info["cmdline"] or []
        if "uvicorn" in argv and port in argv:
            return [process, *process.children(recursive=True)]
    raise SystemExit(f"no uvicorn process on port {port}")


def cpu_seconds(processes: list[psutil.Process]) -> tuple[float, float]:
    """User and system seconds of `processes` so far."""
    times = [process.cpu_times() for process in processes]
    return sum(t.user for t in times), sum(t.system for t in times)


def wrk(argv: list[str]) -> tuple[int, float]:
    """Requests completed and requests/s of one wrk run; any error or non-2xx answer ends the benchmark."""
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
    lines = out.splitlines()
    if any("Non-2xx" in line or "Socket errors" in line for line in lines) or any(
            line.startswith("errors ") and line.split()[1] != "0" for line in lines):
        raise SystemExit("wrk: failed requests\n" + out)
    done = next(int(line.split()[0]) for line in lines if " requests in " in line)
    rate = next(float(line.split()[1]) for line in lines if line.startswith("Requests/sec:"))
    return done, rate


def scripts(base: str, tmp: Path, key: str, check: dict[str, Any]) -> dict[str, list[str]]:
    """The wrk command of each row against one stack; the cache-hit body is answered once first (cached)."""
    body = {**sandboxed(check), "calls": ["system.REQUEST('slot_0')"]}
    (tmp / "hit.json").write_text(json.dumps(body))
    import httpx

    with httpx.Client(base_url=base, timeout=300, headers={"Authorization": f"Bearer {key}"}) as client:
        timed_post(client, "/check-actions", body)
    (tmp / "hit.lua").write_text(WRK_LUA.format(body=tmp / "hit.json", key=key))
    pre, post = json.dumps({**check, "calls": [f"system.REQUEST('{CALL}')"]}).split(CALL)
    (tmp / "interpreter.lua").write_text(WRK_SEQUENTIAL_LUA.format(pre=pre, post=post, key=key))
    return {"cache_hit": ["-s", str(tmp / "hit.lua"), f"{base}/check-actions"],
            "interpreter": ["-s", str(tmp / "interpreter.lua"), base, "--"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, action="append", help="checkout to run (repeat to compare)")
    parser.add_argument("--gateway-processes", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=int, default=4, help="wrk's duration per row, round and checkout")
    parser.add_argument("--connections", type=int, default=32)
    parser.add_argument("--rows", nargs="+", default=["cache_hit", "interpreter"])
    args = parser.parse_args()
    roots = [root.resolve() for root in args.root or [ROOT]]
    check = json.loads((EXAMPLES / "check-actions.json").read_text())
    options = argparse.Namespace(model="tiny", env=[], flood=100, gateway_processes=args.gateway_processes)
    with ExitStack() as running:
        stacks = []
        for root in roots:
            base, tmp, keys = start(root, argparse.Namespace(**{**vars(options), "root": root}), running)
            stacks.append((base, scripts(base, tmp, keys["quiet"], check)))
        samples: dict[tuple[int, str], list[tuple[float, float, float]]] = {}
        for r in range(args.rounds):
            for row in args.rows:
                for step in range(len(stacks)):
                    k = (r + step) % len(stacks)
                    base, commands = stacks[k]
                    processes = gateway_processes(base)
                    before = cpu_seconds(processes)
                    # a new call in every request of every run
                    tail = [f"cpu{k}-{r}-{time.time()}"] if row == "interpreter" else []
                    done, rate = wrk(["wrk", "-t2", f"-c{args.connections}", f"-d{args.seconds}s", *commands[row],
                                      *tail])
                    after = cpu_seconds(processes)
                    user, system = ((a - b) / done * 1000 for a, b in zip(after, before, strict=True))
                    samples.setdefault((k, row), []).append((user, system, rate))
    load = psutil.getloadavg()
    print(f"gateway processes: {args.gateway_processes}; wrk -t2 -c{args.connections} -d{args.seconds}s x "
          f"{args.rounds} rounds; load average at the end {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}")
    for (k, row), taken in sorted(samples.items()):
        ms = [user + system for user, system, _ in taken]
        system_ms = statistics.median(system for _, system, _ in taken)
        print(f"{roots[k]}  {row:12s}  CPU ms/request median {statistics.median(ms):.3f} (system "
              f"{system_ms:.3f}; runs {', '.join(f'{m:.3f}' for m in ms)});  req/s (contended) "
              f"{', '.join(f'{q:.0f}' for _, _, q in taken)}")


if __name__ == "__main__":
    main()
