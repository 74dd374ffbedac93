"""What `precond mcp` adds to a tool call: the refund desk of examples/mcp called directly and through the proxy,
both over stdio with the SDK's client, paired call by call in one run.

    python bench/mcp_proxy_bench.py [--calls 1000] [--modes record,enforce,shadow] [--against OLD] [--json out.json]

Per mode, `--calls` calls alternate a read (`get_order`) and a write (`refund_order`, judged by the read-before-
write rule in `enforce` and `shadow`); each call is made once directly and once through each proxy, in an order
that turns with the call. `--against DIR` (repeatable) adds the proxy of another checkout of the project (an
older version, e.g. `git worktree add` or `git archive` of a commit) to the same run, its process started from
DIR, so that two versions are timed under the same load, call by call. `added` is the through-the-proxy time less
the direct time of the same call: p50/p99. `own_work_ms` is the proxy's own work on a call, from its
`calls.jsonl` (the call's time less the upstream's: judging, recording, logging), the rest of `added` being the
second MCP hop (the proxy's reads, parses and writes of the messages, and the two more process wake-ups).
`proxy_cpu_ms_per_call` is the proxy process's CPU time (user + system, from /proc) over the calls, which other
processes on a shared machine do not add to. Wall-clock figures on a busy machine include other processes' time
slices: say so with them (`load` is the load average at the start).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from pathlib import Path
from typing import Any

from mcp import ClientSession, StdioServerParameters, stdio_client

ROOT = Path(__file__).resolve().parents[1]
DESK = [str(ROOT / "examples" / "mcp" / "refund_desk.py")]
RULES = {"AGENT.refund_order": ["order_id in self.results['get_order']"], "AGENT.send_note": []}
CALLS = (("get_order", {"order_id": "A100"}), ("refund_order", {"order_id": "A100", "amount": 0}))
WARM = 30


def cpu() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.partition(":")[2].strip()
    return platform.processor() or platform.machine()


@asynccontextmanager
async def client(args: list[str], root: Path = ROOT) -> AsyncIterator[ClientSession]:
    params = StdioServerParameters(command=sys.executable, args=args, cwd=str(root), env={"PYTHONPATH": str(root)})
    with open(os.devnull, "w") as quiet:
        async with stdio_client(params, errlog=quiet) as (read, write), ClientSession(read, write) as session:
            await session.initialize()
            yield session


def proxy_cpu_seconds(root: Path) -> float:
    """The CPU time so far of this process's child that runs `precond.cli mcp` from `root` (user + system)."""
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        for child in (task / "children").read_text().split():
            if (b"precond.cli" in Path(f"/proc/{child}/cmdline").read_bytes()
                    and Path(f"/proc/{child}/cwd").resolve() == root):
                fields = Path(f"/proc/{child}/stat").read_text().rpartition(")")[2].split()
                return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    raise RuntimeError("no proxy process found")


def at(values: list[float], share: float) -> float:
    ordered = sorted(values)
    return round(ordered[min(len(ordered) - 1, int(len(ordered) * share))] * 1000, 3)


async def timed(session: ClientSession, n: int) -> float:
    name, arguments = CALLS[n % 2]
    started = time.perf_counter()
    result = await session.call_tool(name, arguments)
    elapsed = time.perf_counter() - started
    assert not result.is_error, result
    return elapsed


def summary(direct_s: list[float], proxied_s: list[float], log: Path, calls: int, cpu_s: float
            ) -> dict[str, Any]:
    added = [p - d for p, d in zip(proxied_s, direct_s, strict=True)]
    logged = [json.loads(line) for line in (log / "calls.jsonl").read_text().splitlines()][-calls:]
    own = [(line["ms"] - line["upstream_ms"]) / 1000 for line in logged]
    return {"proxied_ms": {"p50": at(proxied_s, 0.5), "p99": at(proxied_s, 0.99)},
            "added_ms": {"p50": at(added, 0.5), "p99": at(added, 0.99)},
            "own_work_ms": {"p50": at(own, 0.5), "p99": at(own, 0.99)},
            "proxy_cpu_ms_per_call": round(cpu_s / calls * 1000, 3)}


async def bench_mode(mode: str, calls: int, folder: Path, roots: list[Path]) -> dict[str, Any]:
    """Each call made directly and through each root's proxy, in an order that turns with the call."""
    rules = folder / "rules.json"
    rules.write_text(json.dumps(RULES))
    judged = ["--mode", mode, "--rules", str(rules)] if mode != "record" else []
    logs = [folder / f"{mode}-{n}" for n in range(len(roots))]
    async with AsyncExitStack() as stack:
        direct = await stack.enter_async_context(client(DESK))
        proxies = [await stack.enter_async_context(client(
            ["-m", "precond.cli", "mcp", "--upstream", " ".join([sys.executable, *DESK]), "--log", str(log),
             *judged], root)) for root, log in zip(roots, logs, strict=True)]
        sessions = [direct, *proxies]
        for n in range(WARM):
            for session in sessions:
                await timed(session, n)
        times: list[list[float]] = [[] for _ in sessions]
        cpu_before = [proxy_cpu_seconds(root) for root in roots]
        for n in range(calls):
            turn = n % len(sessions)
            for k in [*range(turn, len(sessions)), *range(turn)]:
                times[k].append(await timed(sessions[k], n))
        cpu_used = [proxy_cpu_seconds(root) - before for root, before in zip(roots, cpu_before, strict=True)]
    return {"mode": mode, "calls": calls, "direct_ms": {"p50": at(times[0], 0.5), "p99": at(times[0], 0.99)},
            "proxies": {str(root): summary(times[0], times[k + 1], logs[k], calls, cpu_used[k])
                        for k, root in enumerate(roots)}}


async def run(args: argparse.Namespace) -> dict[str, Any]:
    results: dict[str, Any] = {"cpu": cpu(), "cores": os.cpu_count(), "load": os.getloadavg(),
                               "python": platform.python_version(), "modes": []}
    roots = [ROOT, *(root.resolve() for root in args.against)]
    with tempfile.TemporaryDirectory() as folder:
        for mode in args.modes.split(","):
            results["modes"].append(await bench_mode(mode, args.calls, Path(folder), roots))
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=int, default=1000, help="paired calls per mode")
    parser.add_argument("--modes", default="record,enforce,shadow")
    parser.add_argument("--against", type=Path, action="append", default=[],
                        help="another checkout of the project (an older version) whose proxy is timed in the same "
                             "run, call by call with this one's (repeatable)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    results = asyncio.run(run(args))
    print(json.dumps(results, indent=1))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
