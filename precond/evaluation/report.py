"""docs/results.md and its plots, regenerated from the cache alone (no inference, no model).

Results of separate runs (SGD now, ALFWorld later, model configs when the model is ready) are merged by
(config, domain), newest wins, so the report always shows everything measured so far.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from precond.evaluation.cache import JsonCache
from precond.evaluation.preconditions import summarize
from precond.evaluation.sweep import Setting, collect

SPEED_DOMAIN = "Restaurants_1"


# ---- storage ---------------------------------------------------------------------------------------------


def store_precondition_results(store: JsonCache, result: dict[str, Any]) -> Path:
    old = store.get("results", "preconditions") or {"rows": []}
    rows = {(r["config"], r["domain"]): r for r in old["rows"]}
    for row in result["rows"]:  # a failed re-run (e.g. no model now) never hides an earlier measurement
        key = (row["config"], row["domain"])
        if not row.get("error") or key not in rows or rows[key].get("error"):
            rows[key] = row
    merged = list(rows.values())
    return store.put({"rows": merged, "summary": summarize(merged)}, "results", "preconditions")


def store_policy_results(store: JsonCache, new: Sequence[dict[str, Any]]) -> Path:
    old = store.get("results", "policy") or []
    rows = {(r["config"], r["domain"]): r for r in old}
    rows.update({(r["config"], r["domain"]): r for r in new})
    return store.put(list(rows.values()), "results", "policy")


def store_sized_results(store: JsonCache, result: dict[str, Any]) -> Path:
    return store.put(result, "results", "next-action")


# ---- tables ----------------------------------------------------------------------------------------------


def _fmt(value: float | None) -> str:
    return "–" if value is None else f"{value:.3f}"


def _markdown(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def precondition_table(summary: Sequence[dict[str, Any]]) -> str:
    """Console table from a run's summary: one line per config and benchmark."""
    rows = [[s["config"], s["benchmark"], str(s["domains"]), *(
        (_fmt(s["macro"]["precision"]), _fmt(s["macro"]["recall"]), _fmt(s["macro"]["f1"]))
        if s["macro"] else ("–", "–", "–")), "; ".join(s["errors"])] for s in summary]
    return _markdown(["config", "benchmark", "domains", "P", "R", "F1", "errors"], rows)


def noise_table(rows: Sequence[dict[str, Any]]) -> str:
    """The noise and sparsity sweep: per setting, F1 per SGD domain, strict (tolerance 0) | tolerant."""
    cells = collect(rows)
    if not cells:
        return "No sweep cached yet (`precond eval preconditions --data <sgd> --configs noise`)."
    always = {r["domain"]: r["macro"]["f1"] for r in rows if r["config"] == "always" and "macro" in r
              and r["benchmark"] == "sgd"}
    tolerances = sorted({s.tolerance for s in cells})
    columns = [*sorted({d for per in cells.values() for d in per} - {"mean"}), "mean"]
    header = ["demos", "errors"] + [f"{d} (tol={t:g})" for d in columns for t in tolerances]
    body = []
    for demos, noise in sorted({(s.demos, s.noise) for s in cells}, key=lambda k: (k[1] > 0, k[0], k[1])):
        line = [str(demos), f"{noise:.0%}"]
        for column in columns:
            for tolerance in tolerances:
                spread = cells.get(Setting(demos, noise, tolerance), {}).get(column)
                line.append(str(spread) if spread else "–")
        body.append(line)
    if always:
        mean = sum(always.values()) / len(always)
        body.append(["`always`", "", *(_fmt(always.get(c, mean)) for c in columns for _ in tolerances)])
    return _markdown(header, body)


def policy_table(rows: Sequence[dict[str, Any]]) -> str:
    body = [[r["domain"], f"`{r['config']}`", str(r["turns"]),
             str(r["actions"]), _fmt(r["f1"]), _fmt(r["compatibility"]),
             f"{_fmt(r.get('compatibility_of_actions'))} ({r.get('non_actions', 0)} non-actions)",
             f"{r['latency_p50_s']:.2f}", f"{r['latency_p95_s']:.2f}",
             f"{r.get('engine_errors', 0)}/{r['requests']}"] for r in rows]
    return _markdown(["domain", "config", "turns", "predictions", "turn F1", "GT compat.",
                      "GT compat. of system actions", "p50 s/request", "p95 s/request", "refused requests"], body)


def _ci(interval: dict[str, float], signed: bool = False) -> str:
    sign = "+" if signed else ""
    return f"{interval['estimate']:{sign}.3f} [{interval['low']:{sign}.3f}, {interval['high']:{sign}.3f}]"


def sized_table(result: dict[str, Any]) -> str:
    """The sized next-action run: estimates with 95% intervals, paired differences to the baseline, latency."""
    body = []
    for r in result["rows"]:
        diff = [_ci(r["f1_diff"], True), _ci(r["compatibility_diff"], True)] if "f1_diff" in r else ["–", "–"]
        body.append([f"`{r['config']}`", str(r["dialogs"]), str(r["turns"]), _ci(r["f1"]),
                     f"{_ci(r['compatibility'])} (n={r['compatibility']['n']})", *diff,
                     f"{r['latency_p50_s']:.2f}", f"{r['latency_p95_s']:.2f}", f"{r['refused']}/{r['requests']}",
                     str(r["nothing_allowed"])])
    return _markdown(["config", "dialogs", "turns", "turn F1 [95% CI]", "GT compat. [95% CI]",
                      "Δ turn F1 vs baseline [95% CI]", "Δ GT compat. [95% CI]", "p50 s/request",
                      "p95 s/request", "refused", "nothing allowed"], body)


def _sized_section(result: dict[str, Any] | None) -> list[str]:
    if not result:
        return ["No sized next-action run cached yet (`precond eval next-action`)."]
    baseline = next((r["vs"] for r in result["rows"] if "vs" in r), "–")
    partial = "" if result.get("complete", True) else (
        " **Partial run**: the sample was not finished within the time available; the table holds the dialogs "
        "every configuration finished (domains interleaved dialog by dialog, so all four are in it), and "
        "`precond eval next-action` continues it from the cache.")
    return [
        f"All four SGD domains, test dialogs drawn whole in a seeded order (seed {result['seed']}) until each "
        f"domain has at least {result['turns_per_domain']} system turns; every configuration runs on the same "
        f"turns. Inferred preconditions: `{result['inferred_from']}` (cached). Intervals: percentile "
        "bootstrap over dialogs (2,000 resamples; precond/evaluation/stats.py); Δ: paired bootstrap of the difference "
        f"to `{baseline}` on the same dialogs. Latency: per request (one segment of a turn, up to 5 actions), "
        "as the evaluation run saw it (1-2 threads of a 2-core machine, other work beside it); the latency "
        f"targets are measured by bench/pipeline_bench.py on a quiet machine (docs/model-speed.md).{partial}\n",
        sized_table(result),
        *_training_table(result.get("training") or {}),
    ]


def _training_table(training: dict[str, dict[str, Any]]) -> list[str]:
    """What the BC rows' adapters cost: one LoRA training per domain on its demonstrations (evaluation/bc.py)."""
    if not training:
        return []
    body = [[name, str(t["examples"]), str(t["action_lines"]), str(t["steps"]), f"{t['final_loss']:.3f}",
             f"{t['seconds']:.0f}", f"{t['adapter_bytes'] / 1e6:.1f}"] for name, t in sorted(training.items())]
    return ["\nBC adapters (`precond train-policy` defaults: LoRA rank 8 on the attention projections, one "
            "demonstration per step, all cores; peak memory: bench/train_policy_bench.py):\n",
            _markdown(["domain", "demonstrations", "action lines", "steps", "last loss", "training s",
                       "adapter MB"], body) + "\n"]


def alfworld_next_table(result: dict[str, Any]) -> str:
    body = []
    for r in result["rows"]:
        diff = [_ci(r["admissible_diff"], True), _ci(r["expert_diff"], True)] if "expert_diff" in r else ["–", "–"]
        body.append([f"`{r['config']}`", str(r["episodes"]), str(r["steps"]), _ci(r["admissible"]),
                     _ci(r["expert"]), *diff, f"{r['latency_p50_s']:.2f}", f"{r['latency_p95_s']:.2f}",
                     str(r["refused"])])
    return _markdown(["config", "trajectories", "steps", "admissible [95% CI]", "expert match [95% CI]",
                      "Δ admissible", "Δ expert match", "p50 s", "p95 s", "refused"], body)


def _alfworld_section(result: dict[str, Any] | None) -> list[str]:
    if not result:
        return ["No ALFWorld next-action run cached yet (`precond eval next-action-alfworld`)."]
    return [
        f"\nALFWorld valid_unseen: {result['episodes']} trajectories drawn in a seeded order (seed "
        f"{result['seed']}), {result['steps']} action steps each, spread evenly; one action predicted per step, "
        "with the demonstration of the episode's task type. Admissible: the simulator accepted the command in "
        f"that state. Inferred preconditions: `{result['inferred_from']}`. Intervals: bootstrap over "
        "trajectories. `/react`: the demonstration carries ReAct's hand-written thoughts "
        "(evaluation/react_thoughts.py) and the model writes one before the action (`options.think`); `/bc`: the "
        "model fine-tuned on the twelve ALFWorld demonstrations, shown none.\n",
        alfworld_next_table(result),
        *_training_table(result.get("training") or {}),
    ]


NEXT_ACTION_HEADING = "## Next action at size: modes compared with intervals"
CHOICE = Path(__file__).with_name("next_action_choice.md")


def next_action_section(store: JsonCache, plot: Path | None) -> str:
    """The sized next-action runs (SGD and ALFWorld), the reading of them, and their plot."""
    parts = [NEXT_ACTION_HEADING + "\n", *_sized_section(store.get("results", "next-action")),
             *_alfworld_section(store.get("results", "next-action-alfworld")),
             "\n" + CHOICE.read_text(encoding="utf-8") if CHOICE.exists() else ""]
    if plot is not None:
        parts.append(f"\n![{plot.stem}](img/{plot.name})\n")
    return "\n".join(parts)


def write_next_action_section(store: JsonCache, out: Path) -> None:
    """Replace (or add, before `## Speed`) the next-action section of an existing report, and its plot.

    The rest of the report comes from runs this cache may not hold (`write_report` regenerates it all);
    a next-action run must not wipe them.
    """
    from precond.evaluation.plots import sized_plot

    sized = store.get("results", "next-action")
    img = out.parent / "img"
    img.mkdir(parents=True, exist_ok=True)
    section = next_action_section(store, sized_plot(sized["rows"] if sized else [], img))
    text = out.read_text(encoding="utf-8") if out.exists() else "# Evaluation results\n"
    start = text.find(NEXT_ACTION_HEADING)
    if start >= 0:
        end = text.find("\n## ", start + len(NEXT_ACTION_HEADING))
        text = text[:start] + section.rstrip() + "\n" + (text[end:] if end >= 0 else "")
    else:
        at = text.find("\n## Speed")
        at = len(text) if at < 0 else at + 1
        text = text[:at] + section.rstrip() + "\n\n" + text[at:]
    out.write_text(text, encoding="utf-8")


def speed_table(rows: Sequence[dict[str, Any]]) -> str:
    chosen = [r for r in rows if r["domain"] == SPEED_DOMAIN and r.get("seconds")
              and "demos=" not in r["config"] and "maxrate=" not in r["config"]]
    phases = list(dict.fromkeys(p for r in chosen for p in r["seconds"]))
    body = [[f"`{r['config']}`", *(f"{r['seconds'].get(p, 0.0):.2f}" for p in phases), f"{r['wall_s']:.1f}"]
            for r in chosen]
    return _markdown(["config", *(f"{p} s" for p in phases), "total s"], body)


# ---- machine ---------------------------------------------------------------------------------------------


def cpu_model() -> str:
    """The CPU's name as /proc/cpuinfo gives it (reports and benchmarks state the machine they ran on)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _memory_gib() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                return f"{int(line.split()[1]) / 2**20:.1f} GiB"
    except OSError:
        pass
    return "unknown"


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, check=False)
    except OSError:
        return "unknown"
    status = subprocess.run(["git", "status", "--porcelain"], capture_output=True, text=True, check=False)
    dirty = status.stdout
    commit = out.stdout.strip() if out.returncode == 0 else "no commit yet"
    return commit + (" (with uncommitted changes)" if dirty.strip() else "")


def machine() -> str:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    return (f"- machine: {cpu_model()}, {cores} cores available, {_memory_gib()} RAM, no GPU, "
            f"Python {platform.python_version()}\n- generated: {now}\n- git commit: {_git_commit()}")


def sandbox_bench(script: Path, store: JsonCache) -> str:
    """The sandbox benchmark's figures, run once and cached like everything else (it takes a minute)."""
    data = store.get("bench", "sandbox")
    if data is None:
        if not script.exists():
            return f"`{script}` is not present; no sandbox throughput was measured."
        path = store.path("bench", "sandbox")
        path.parent.mkdir(parents=True, exist_ok=True)
        root = os.pathsep.join(filter(None, [os.getcwd(), os.environ.get("PYTHONPATH")]))
        run = subprocess.run([sys.executable, str(script), "--json", str(path)], capture_output=True,
                             text=True, check=False, timeout=900, env={**os.environ, "PYTHONPATH": root})
        if run.returncode != 0 or not path.exists():
            return f"`{script} --json` failed (exit {run.returncode}): {run.stderr.strip()[-300:]}"
        data = store.get("bench", "sandbox")
    figures = json.dumps(data, indent=1)
    return f"From `{script}` (cached in the cache's bench/sandbox.json):\n\n```json\n{figures}\n```"


# ---- report ----------------------------------------------------------------------------------------------


ANALYSIS = Path(__file__).with_name("analysis.md")
NOISE_TEXT = (
    "Macro F1 (mean ± standard deviation over 3 seeds) of strict validation (tolerance 0, the paper) and "
    "evidence-weighted validation (the default tolerance), from `precond eval preconditions --configs noise`: "
    "fewer demonstrations drawn at random (clean), and all ten with agent errors injected at a share of the "
    "system steps (evaluation/noise.py: a re-asked informed slot, an act against the last API result, a dropped "
    "or a duplicated step; test dialogs and ground truth untouched). Model-free (`enumerate`): the model path "
    "takes about 25 s per inference on the 2-core evaluation machine, too slow for 200 inferences.\n")


NOISE_HEADING = "## Noise and sparsity (SGD, `enumerate/recency`)"


def noise_section(rows: Sequence[dict[str, Any]], img: Path) -> str:
    """The sweep's table and plot, as one section (also written alone: `write_noise_section`)."""
    from precond.evaluation.plots import noise_plot

    plot = noise_plot(rows, img)
    figure = f"\n![{plot.stem}](img/{plot.name})\n" if plot else ""
    return f"{NOISE_HEADING}\n\n{NOISE_TEXT}\n{noise_table(rows)}\n{figure}"


def write_noise_section(store: JsonCache, out: Path) -> None:
    """Regenerate only the noise and sparsity section of an existing report, from the cached sweep: the rest
    stays as the last full run wrote it."""
    rows = (store.get("results", "preconditions") or {"rows": []})["rows"]
    img = out.parent / "img"
    img.mkdir(parents=True, exist_ok=True)
    replace_section(out, NOISE_HEADING, noise_section(rows, img), before=NEXT_ACTION_HEADING)


def replace_section(out: Path, heading: str, section: str, before: str, stop: str | None = None) -> None:
    """Write `section` (starting with `heading`) in place of the report's section of that heading, or, when the
    report has none, in front of the section headed `before` (at the end without one). The section ends at the
    next `## ` heading, or at `stop` where that comes first (a subsection another command writes)."""
    text = out.read_text(encoding="utf-8") if out.exists() else ""
    start = text.find(heading)
    if start < 0:
        anchor = text.find(before)
        start = end = anchor if anchor >= 0 else len(text)
    else:
        markers = ["\n## ", *([f"\n{stop}"] if stop else [])]
        found = [at for at in (text.find(m, start + len(heading)) for m in markers) if at >= 0]
        end = min(found) + 1 if found else len(text)
    out.write_text(text[:start] + section + "\n" + text[end:], encoding="utf-8")


HEADER = (
    "# Evaluation results\n\n"
    "Generated by `precond eval all` (`precond eval report`: from the cache alone); do not edit by hand.\n"
    "Definitions: `precond/evaluation/metrics.py` (edge cases), points and argument domains: "
    "`precond/evaluation/domains.py`.\n"
    "Each section holds the current table of one benchmark, with the command that regenerates it and how its\n"
    "configurations were chosen; figures a newer measurement replaced are in CHANGELOG.md (\"Earlier history\").\n")


def speed_section(store: JsonCache, bench: Path) -> str:
    """The inference phases of every cached configuration on one domain, and the sandbox's throughput."""
    pre = (store.get("results", "preconditions") or {"rows": []})["rows"]
    return "\n".join([
        "## Speed\n",
        f"Inference phases on {SPEED_DOMAIN} (seconds, from `InferResponse.stats.seconds`):\n",
        speed_table(pre),
        "\nNext-action latency: see the next-action section. The model runtime (dtypes, threads, and the same "
        "pipeline on llama.cpp side by side, measured with bench/ on a quiet machine): "
        "[model-speed.md](model-speed.md).\n",
        "### Sandbox throughput\n",
        sandbox_bench(bench, store),
        "",
    ])


def write_report(store: JsonCache, out: Path, bench: Path) -> None:
    """The whole report in its layout (precond/evaluation/layout.py), from the cache and the report as it was."""
    from precond.evaluation.layout import Inputs, sections

    img = out.parent / "img"
    img.mkdir(parents=True, exist_ok=True)
    old = out.read_text(encoding="utf-8") if out.exists() else ""
    body = "".join(sections(Inputs(store, img, bench), old))
    out.write_text(f"{HEADER}\n{machine()}\n\n{body}".rstrip() + "\n", encoding="utf-8")
