"""`precond eval next-action-alfworld`: next actions in ALFWorld, scored by what the simulator accepts.

At sampled action steps of valid_unseen trajectories, the history is the episode so far (its program up to
that step) and the configuration predicts one action. It is scored two ways: admissible (the simulator's
admissible commands in that very state, `test_admissible_commands.json`, contain it) and expert match (it is
the action the expert took). Trajectories are drawn in a seeded order and steps spread evenly over each one;
the trajectory is the bootstrap unit. Cached per trajectory and configuration, so a run resumes.
"""

from __future__ import annotations

import ast
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from tqdm import tqdm

from precond.evaluation import react_thoughts
from precond.evaluation.cache import JsonCache
from precond.evaluation.domains import action_positions, parse_command
from precond.evaluation.metrics import percentile
from precond.evaluation.policy import PolicyConfig, PolicyEngine
from precond.evaluation.stats import bootstrap, paired_difference
from precond_client.schemas import NextActionOptions, NextActionRequest
from precond_client.schemas.errors import PrecondError


@dataclass(frozen=True)
class Episode:
    id: str
    program: str
    demonstration: str
    react_demonstration: str
    """The same demonstration with ReAct's hand-written thoughts (precond/evaluation/react_thoughts.py)."""
    steps: list[tuple[int, dict[str, Any]]]
    """(body position, action step) of the steps predicted."""
    admissible: list[list[str]]


def sample_episodes(trajectories: Sequence[dict[str, Any]], demos: Sequence[dict[str, Any]],
                    admissible: dict[str, list[list[str]]], episodes: int, steps: int, seed: int) -> list[Episode]:
    """Seeded trajectories with admissible commands, `steps` in-spec action steps each, spread evenly.

    The demonstration shown is the one of the episode's task type (the agent knows its task)."""
    order = [t for t in trajectories if t["id"] in admissible]
    random.Random(seed).shuffle(order)
    by_type = {d["task_type"]: d for d in reversed(demos)}  # the first of each type
    thoughts = react_thoughts.load()
    out = []
    for trajectory in order[:episodes]:
        found = [(p, s) for p, s in action_positions(trajectory) if p >= 0]
        picks = sorted({round(k * (len(found) - 1) / max(1, steps - 1)) for k in range(steps)}) if found else []
        demo = by_type.get(trajectory["task_type"], demos[0])
        react = react_thoughts.with_thoughts(demo["program"], thoughts.get(demo["source"]["key"], []))
        out.append(Episode(trajectory["id"], trajectory["program"], demo["program"], react,
                           [found[k] for k in picks], admissible[trajectory["id"]]))
    return out


def history_before(program: str, position: int) -> str:
    """The episode's program up to (not including) the body statement at `position`."""
    function = ast.parse(program).body[0]
    assert isinstance(function, ast.FunctionDef)
    lines = program.splitlines()
    return "\n".join(lines[: function.body[position].lineno - 1]) + "\n"


def predicted_command(call: str | None) -> tuple[str, tuple[str, ...]] | None:
    """`agent.take('apple 1', 'table 1')` → ('take', ('apple 1', 'table 1')); None for anything else."""
    try:
        node = ast.parse(call or "", mode="eval").body
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            return node.func.attr, tuple(str(ast.literal_eval(a)) for a in node.args)
    except (SyntaxError, ValueError):
        pass
    return None


def _predict(engine: PolicyEngine, spec: str, config: PolicyConfig, preconditions: dict[str, list[str]],
             episode: Episode, position: int, step: dict[str, Any], seed: int,
             replayed: Callable[[], float]) -> dict[str, Any]:
    react = config.policy == "react"
    options = NextActionOptions(max_actions=1, verify=config.verify, seed=seed, mode=config.mode,  # type: ignore[arg-type]
                                choose_by=config.choose_by,  # type: ignore[arg-type]
                                preconditions_in_prompt=config.in_prompt, think=react,
                                fallback="greedy" if config.mode == "sample" else "none")
    shown = [episode.react_demonstration if react else episode.demonstration][: config.shots]
    request = NextActionRequest(spec=spec, preconditions=preconditions if config.source != "none" else {},
                                demonstrations=shown,
                                history=history_before(episode.program, position), options=options)
    start = time.perf_counter()
    try:
        action = engine.next_action(request).actions[0]
        call = action.call if action.call is not None else None if action.nothing_allowed else (
            action.rejected[0].call if action.rejected else None)
        error, thoughts = None, action.thoughts
    except PrecondError as exc:
        call, error, thoughts = None, f"{exc.kind}: {exc.message}", []
    return {"call": call, "seconds": time.perf_counter() - start + replayed(), "error": error, "thoughts": thoughts}


def scored(prediction: dict[str, Any], episode: Episode, step: dict[str, Any]) -> dict[str, Any]:
    """The prediction with its scores, from its call: admissible (a command the simulator offered in that state;
    a line that is no command, e.g. cut off or a comment, never is) and expert (the expert's own command)."""
    offered = {parse_command(c) for c in episode.admissible[step["t"] - 1]} | {(step["fn"], tuple(step["args"]))}
    command = predicted_command(prediction["call"])
    expert = (step["fn"], tuple(step["args"]))
    return prediction | {"admissible": command is not None and command in offered, "expert": command == expert,
                         "episode": episode.id}


def run(engine_for: Callable[[PolicyConfig], PolicyEngine], spec: str, episodes: Sequence[Episode],
        configs: Sequence[PolicyConfig], preconditions: Callable[[PolicyConfig], dict[str, list[str]]],
        cache: JsonCache, seed: int = 0, replayed: Callable[[], float] = lambda: 0.0
        ) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = {c.name: [] for c in configs}
    total = sum(len(e.steps) for e in episodes) * len(configs)
    with tqdm(total=total, unit="request", desc="next-action alfworld", smoothing=0.05) as bar:
        for episode in episodes:
            for config in configs:
                done: dict[str, Any] = cache.get("alfworld-next", config.name, episode.id) or {}
                for position, step in episode.steps:
                    if str(position) not in done:
                        done[str(position)] = _predict(engine_for(config), spec, config, preconditions(config),
                                                       episode, position, step, seed, replayed)
                        cache.put(done, "alfworld-next", config.name, episode.id)
                    out[config.name].append(scored(done[str(position)], episode, step))
                    bar.update(1)
    return out


def summarize(results: dict[str, list[dict[str, Any]]], baseline: str) -> list[dict[str, Any]]:
    """Per configuration: share admissible and expert match with 95% intervals (trajectories resampled)."""
    def per_episode(rows: Sequence[dict[str, Any]], key: str) -> dict[str, list[float]]:
        units: dict[str, list[float]] = {}
        for r in rows:
            units.setdefault(r["episode"], []).append(1.0 if r[key] else 0.0)
        return units

    out = []
    for name, rows in results.items():
        row: dict[str, Any] = {"config": name, "episodes": len({r["episode"] for r in rows}), "steps": len(rows),
                               "latency_p50_s": percentile([r["seconds"] for r in rows], 50),
                               "latency_p95_s": percentile([r["seconds"] for r in rows], 95),
                               "refused": sum(1 for r in rows if r["error"])}
        for key in ("admissible", "expert"):
            i = bootstrap(list(per_episode(rows, key).values()))
            row[key] = {"estimate": i.estimate, "low": i.low, "high": i.high, "n": i.n}
            if name != baseline and baseline in results:
                d = paired_difference(per_episode(results[baseline], key), per_episode(rows, key))
                row[f"{key}_diff"] = {"estimate": d.estimate, "low": d.low, "high": d.high, "n": d.n}
        out.append(row)
    return out
