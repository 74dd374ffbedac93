"""The embedded guard (`precond_client.guard.Guard`) and its adapters, on tau-bench's airline runs.

    python bench/guard_bench.py [--data ../shared/data/tau-airline] [--repeat 2000] [--calls 40] [--json out.json]
    SANDBOX_TIMEOUT_S=30 python bench/guard_bench.py --retail ../shared/data/tau-retail [--repeat 200]

- `check`: a state-changing call judged after a history of about 12 KB (its messages as JSON), the state already
  built: every such call of the runs, each judged `--repeat` times; p50/p99 of single checks.
- `add`: each message of every run added to its session (the state updated, nothing replayed): p50/p99/max.
- `openai_agents` and `langgraph`: a scripted model's run of `--calls` tool calls through the framework with its
  tools bare and with them guarded (`protect`, `guarded_tool_node`), alternated (medians of `--rounds`); what
  guarding adds per call, beside the embedded guard's own work in such a run (`guard_cpu_ms_per_call`: one check
  and two messages added per call, alone). `guard_in_run_cpu_ms_per_call` is that work timed inside the guarded
  runs (the guard wrapped, `TimedGuard`), and `adapter_own_cpu_us_per_call` the rest of the added CPU: the
  adapter's conversions and bookkeeping and the framework's own guardrail machinery (the figure against the goal
  of 100 µs per guarded call). `conversion_cpu_us_per_step`: the adapter's conversion of one step's new items (a
  call and its result), timed alone.

Each figure is wall-clock and CPU time (the thread's for single checks, the process's for runs): on a machine
shared with other work, wall-clock tails are the other processes' time slices.

- `retail_check` (with `--retail`, in place of the rest): the rules the learner infers from tau-bench retail's 150
  runs with every label (bench/tool_retail_bench.py's request), then every labelled state-changing call judged
  `--repeat` times on the history before it: p50/p99 of single checks.

The airline rules are the forms the learner writes, for the state-changing tools: the read before the write, fields of
the read result (the cancellation clause's disjunction), the call's arguments against them. The service's path
(`/check-actions`, a queue round trip) is bench/tool_check_bench.py.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import statistics
import sys
import time
import timeit
from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from precond.convert.openai import convert  # noqa: E402
from precond_client.guard import Guard, Judge, Session  # noqa: E402
from precond_client.schemas import CallVerdict  # noqa: E402

READ = "reservation_id in self.results['get_reservation_details']"
GOT = "self.results['get_reservation_details'][reservation_id]"
RULES = {
    "AGENT.cancel_reservation": [READ, f"{READ} and ({GOT}['cabin'] == 'business' or {GOT}['insurance'] == 'yes' "
                                       f"or {GOT}['created_at'] >= '2024-05-14T15:00:00')"],
    "AGENT.update_reservation_flights": [READ, f"{READ} and ({GOT}['cabin'] != 'basic_economy' or cabin == "
                                               f"{GOT}['cabin'])"],
    "AGENT.update_reservation_baggages": [READ, f"{READ} and total_baggages >= {GOT}['total_baggages']"],
    "AGENT.update_reservation_passengers": [READ, f"{READ} and len(passengers) == len({GOT}['passengers'])"],
    "AGENT.send_certificate": ["user_id in self.results['get_user_details']"],
    "AGENT.book_reservation": ["user_id in self.results['get_user_details']", "len(passengers) <= 5"],
}
WRITES = {a.partition(".")[2] for a in RULES}
HISTORY_BYTES = (11_000, 13_000)


def cpu() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.partition(":")[2].strip()
    return platform.processor() or platform.machine()


def percentiles(samples: list[float], cpu: list[float]) -> dict[str, float]:
    """Wall-clock p50/p99/max, and the same of the thread's CPU time (what a shared machine's other processes
    do not add: on the 2-core VM beside other work, wall-clock tails are other processes' time slices)."""
    ordered, used = sorted(samples), sorted(cpu)

    def at(values: list[float], share: float) -> float:
        return values[min(len(values) - 1, int(len(values) * share))] * 1e6

    return {"n": len(ordered), "p50_us": at(ordered, 0.5), "p99_us": at(ordered, 0.99), "max_us": ordered[-1] * 1e6,
            "cpu_p50_us": at(used, 0.5), "cpu_p99_us": at(used, 0.99), "mean_us": statistics.fmean(samples) * 1e6}


def timed(action: Callable[[], object], samples: list[float], cpu: list[float]) -> None:
    started, used = time.perf_counter(), time.thread_time()
    action()
    samples.append(time.perf_counter() - started)
    cpu.append(time.thread_time() - used)


def guarded_points(guard: Guard, runs: list[list[dict[str, Any]]]) -> list[tuple[Session, dict[str, Any]]]:
    """(the session after the history, the call) for each state-changing call after about 12 KB of messages."""
    points = []
    for run in runs:
        for at, message in enumerate(run):
            for call in message.get("tool_calls") or []:
                size = len(json.dumps(run[:at]))
                if call["function"]["name"] in WRITES and HISTORY_BYTES[0] <= size <= HISTORY_BYTES[1]:
                    points.append((guard.session(run[:at]), call["function"]))
    return points


def bench_check(guard: Guard, runs: list[list[dict[str, Any]]], repeat: int) -> dict[str, Any]:
    return timed_checks(guarded_points(guard, runs), repeat)


def timed_checks(points: list[tuple[Session, dict[str, Any]]], repeat: int) -> dict[str, Any]:
    """Each call judged `repeat` times after its history: the verdicts, p50/p99 of single checks."""
    samples: list[float] = []
    cpu: list[float] = []
    verdicts = {"allowed": 0, "refused": 0}
    for session, call in points:
        verdict = session.check(call["name"], call["arguments"])
        verdicts["allowed" if verdict.allowed else "refused"] += 1
        for _ in range(repeat):
            timed(partial(session.check, call["name"], call["arguments"]), samples, cpu)
    return {"calls": len(points), **verdicts, **percentiles(samples, cpu)}


def bench_add(guard: Guard, runs: list[list[dict[str, Any]]], repeat: int) -> dict[str, Any]:
    """Every message of every run, by kind: a tool's result is parsed and checked as JSON, the rest is small."""
    kinds: dict[str, tuple[list[float], list[float]]] = {}
    for _ in range(max(1, repeat // 100)):
        for run in runs:
            session = guard.session()
            for message in run:
                kind = "tool result" if message.get("role") == "tool" else "other"
                samples, cpu = kinds.setdefault(kind, ([], []))
                timed(partial(session.add, message), samples, cpu)
    every = ([t for s, _ in kinds.values() for t in s], [t for _, c in kinds.values() for t in c])
    return {"messages": sum(len(r) for r in runs), **percentiles(*every),
            **{kind: percentiles(*found) for kind, found in kinds.items()}}


RESERVATION = json.dumps({"reservation_id": "R1", "user_id": "u1", "cabin": "business", "insurance": "no",
                          "created_at": "2024-05-01T10:00:00", "total_baggages": 1, "passengers": [{}]})


def script(calls: int) -> list[tuple[str, dict[str, Any]]]:
    """A read, then writes that the rules allow: every call is judged and runs."""
    steps: list[tuple[str, dict[str, Any]]] = [("get_reservation_details", {"reservation_id": "R1"})]
    while len(steps) < calls:
        steps.append(("update_reservation_baggages", {"reservation_id": "R1", "total_baggages": 2,
                                                      "nonfree_baggages": 0, "payment_id": "gift_card_1"}))
    return steps


def paired(bare: Callable[[], float], guarded: Callable[[], float], rounds: int) -> dict[str, float]:
    """Medians of alternated runs: wall-clock and the process's CPU time (its threads too), seconds per run."""
    times: dict[str, list[float]] = {"bare": [], "guarded": [], "bare_cpu": [], "guarded_cpu": []}
    for _ in range(rounds):
        for name, run in (("bare", bare), ("guarded", guarded)):
            used = time.process_time()
            times[name].append(run())
            times[f"{name}_cpu"].append(time.process_time() - used)
    return {name: statistics.median(values) for name, values in times.items()}


def agents_run(guard: Judge | None, calls: int) -> float:
    from agents import Agent, Runner, function_tool
    from agents.testing import ScriptedModel, assistant_message, function_call

    from precond_client.adapters.openai_agents import protect

    @function_tool
    def get_reservation_details(reservation_id: str) -> str:
        """Read a reservation."""
        return RESERVATION

    @function_tool
    def update_reservation_baggages(reservation_id: str, total_baggages: int, nonfree_baggages: int,
                                    payment_id: str) -> str:
        """Change bags."""
        return RESERVATION

    steps = [[function_call(name, args, call_id=f"c{n}")] for n, (name, args) in enumerate(script(calls))]
    agent = Agent(name="airline", model=ScriptedModel([*steps, [assistant_message("done")]]),
                  tools=[get_reservation_details, update_reservation_baggages])
    agent = protect(agent, guard) if guard is not None else agent
    started = time.perf_counter()
    result = asyncio.run(Runner.run(agent, "bags", max_turns=calls + 2))
    assert result.final_output == "done"
    return time.perf_counter() - started


def langgraph_run(guard: Judge | None, calls: int) -> float:
    from langchain_core.language_models.fake_chat_models import GenericFakeChatModel
    from langchain_core.messages import AIMessage, HumanMessage
    from langchain_core.tools import tool
    from langgraph.graph import START, MessagesState, StateGraph
    from langgraph.prebuilt import ToolNode, tools_condition

    from precond_client.adapters.langgraph import guarded_tool_node

    @tool
    def get_reservation_details(reservation_id: str) -> str:
        """Read a reservation."""
        return RESERVATION

    @tool
    def update_reservation_baggages(reservation_id: str, total_baggages: int, nonfree_baggages: int,
                                    payment_id: str) -> str:
        """Change bags."""
        return RESERVATION

    answers = [AIMessage("", tool_calls=[{"name": name, "args": args, "id": f"c{n}"}])
               for n, (name, args) in enumerate(script(calls))]
    model = GenericFakeChatModel(messages=iter([*answers, AIMessage("done")]))
    tools = [get_reservation_details, update_reservation_baggages]
    graph = StateGraph(MessagesState)
    graph.add_node("model", lambda state: {"messages": [model.invoke(state["messages"])]})
    graph.add_node("tools", guarded_tool_node(tools, guard) if guard is not None else ToolNode(tools))
    graph.add_edge(START, "model")
    graph.add_conditional_edges("model", tools_condition)
    graph.add_edge("tools", "model")
    app = graph.compile()
    started = time.perf_counter()
    final = app.invoke({"messages": [HumanMessage("bags")]}, {"recursion_limit": 4 * calls + 10,
                                                               "configurable": {"thread_id": "t"}})
    assert final["messages"][-1].content == "done"
    return time.perf_counter() - started


def guard_work(guard: Guard, calls: int) -> float:
    """What the embedded guard itself does in one scripted run (CPU seconds): each call judged, each message
    added."""
    session = guard.session([{"role": "user", "content": "bags"}])
    started = time.thread_time()
    for n, (name, args) in enumerate(script(calls)):
        session.check(name, args)
        session.add({"role": "assistant", "content": None,
                     "tool_calls": [{"id": f"c{n}", "function": {"name": name, "arguments": json.dumps(args)}}]})
        session.add({"role": "tool", "tool_call_id": f"c{n}", "name": name, "content": RESERVATION})
    return time.thread_time() - started


class TimedGuard:
    """The guard as the adapters take it (`Judge`), with the CPU time of its own work (each check, each message
    added) summed in `used`, in the thread that does it: what the adapter adds beyond that is its own."""

    def __init__(self, guard: Guard) -> None:
        self.guard = guard
        self.fail_closed = guard.fail_closed
        self.used = 0.0

    @property
    def name(self) -> str:
        return self.guard.name

    def session(self) -> TimedSession:
        return TimedSession(self, self.guard.session())


class TimedSession:
    def __init__(self, timed: TimedGuard, session: Session) -> None:
        self.timed = timed
        self.session = session

    def add(self, message: Mapping[str, Any]) -> None:
        started = time.thread_time()
        try:
            self.session.add(message)
        finally:
            self.timed.used += time.thread_time() - started

    def check(self, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict:
        started = time.thread_time()
        try:
            return self.session.check(name, arguments)
        finally:
            self.timed.used += time.thread_time() - started

    async def acheck(self, name: str, arguments: str | Mapping[str, Any]) -> CallVerdict:
        return self.check(name, arguments)


def conversion_us() -> dict[str, float]:
    """Each adapter's conversion of one step's new items (a call and its result) to chat messages, CPU µs (the
    best of 5 x 1,000): the part of its own work that grows with what a step adds."""
    from langchain_core.messages import AIMessage, ToolMessage

    from precond_client.adapters import langgraph, openai_agents

    name, args = script(2)[1]
    items: list[Any] = [{"type": "function_call", "call_id": "c1", "name": name, "arguments": json.dumps(args)},
                        {"type": "function_call_output", "call_id": "c1", "output": RESERVATION}]
    messages = [AIMessage("", tool_calls=[{"name": name, "args": args, "id": "c1"}]),
                ToolMessage(RESERVATION, tool_call_id="c1", name=name)]
    steps = {"openai_agents": partial(openai_agents.chat_messages, items),
             "langgraph": partial(langgraph.chat_messages, messages)}
    return {framework: min(timeit.repeat(step, timer=time.thread_time, number=1000, repeat=5)) * 1e3
            for framework, step in steps.items()}


def bench_adapters(guard: Guard, calls: int, rounds: int) -> dict[str, Any]:
    own = statistics.median(guard_work(guard, calls) for _ in range(rounds)) / calls
    results: dict[str, Any] = {"calls_per_run": calls, "rounds": rounds, "guard_cpu_ms_per_call": own * 1e3}
    runs: dict[str, Callable[[Any, int], float]] = {"openai_agents": agents_run, "langgraph": langgraph_run}
    converting = conversion_us()
    for name, run in runs.items():
        run(guard, calls)  # warm-up: imports, the frameworks' first-use work
        timed = TimedGuard(guard)
        medians = paired(partial(run, None, calls), partial(run, timed, calls), rounds)
        per_call = {key: value / calls * 1e3 for key, value in medians.items()}
        added_cpu = per_call["guarded_cpu"] - per_call["bare_cpu"]
        in_run = timed.used / rounds / calls * 1e3
        results[name] = {f"{key}_ms_per_call": value for key, value in per_call.items()} | {
            "added_ms_per_call": per_call["guarded"] - per_call["bare"], "added_cpu_ms_per_call": added_cpu,
            "guard_in_run_cpu_ms_per_call": in_run, "adapter_own_cpu_us_per_call": (added_cpu - in_run) * 1e3,
            "conversion_cpu_us_per_step": converting[name]}
    return results


def retail_points(guard: Guard, data: Path) -> list[tuple[Session, dict[str, Any]]]:
    """(the session after the history, the call) for each labelled state-changing call of tau-retail's runs."""
    runs = {(r["task_id"], r["trial"]): r["traj"] for r in json.loads((data / "trajectories.json").read_text())}
    points = []
    for label in json.loads((data / "labels.json").read_text()):
        run = runs[(label["task_id"], label["trial"])]
        at = label["message_index"]
        call = next(c["function"] for c in run[at]["tool_calls"] if c["function"]["name"] == label["tool"])
        points.append((guard.session(run[:at]), call))
    return points


def bench_retail(data: Path, repeat: int) -> dict[str, Any]:
    """The retail rules inferred once (all runs, every label), then `bench_check`'s timing on the labelled calls."""
    from tool_retail_bench import WRITES as RETAIL_WRITES
    from tool_retail_bench import request

    from precond.engine.factory import build_engine

    records = json.loads((data / "trajectories.json").read_text())
    converted = convert(records, json.loads((data / "tools.json").read_text()), "trajectories.json",
                        "tools.json", set(RETAIL_WRITES))
    labels = json.loads((data / "labels.json").read_text())
    rules = build_engine(with_model=False).infer(request(converted, labels, None)).preconditions
    guard = Guard(converted.spec, rules)
    return {"rules": sum(len(r) for r in rules.values()), **timed_checks(retail_points(guard, data), repeat)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "tau-airline")
    parser.add_argument("--repeat", type=int, default=2000, help="checks per call")
    parser.add_argument("--calls", type=int, default=40, help="tool calls per scripted adapter run")
    parser.add_argument("--rounds", type=int, default=15, help="alternated bare/guarded adapter runs")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--retail", type=Path, help="time the check on the rules inferred from this tau-retail data")
    args = parser.parse_args()
    if args.retail:
        results = {"cpu": cpu(), "python": platform.python_version(), "retail_check": bench_retail(args.retail,
                                                                                                    args.repeat)}
        print(json.dumps(results, indent=1))
        return
    records = json.loads((args.data / "trajectories.json").read_text())
    converted = convert(records, json.loads((args.data / "tools.json").read_text()))
    guard = Guard(converted.spec, RULES)
    runs = [record["traj"] for record in records]
    results = {"cpu": cpu(), "python": platform.python_version(),
               "check": bench_check(guard, runs, args.repeat), "add": bench_add(guard, runs, args.repeat),
               "adapters": bench_adapters(guard, args.calls, args.rounds)}
    print(json.dumps(results, indent=1))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
