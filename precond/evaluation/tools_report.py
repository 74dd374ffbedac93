"""The tool-calling section of docs/results.md (`precond eval tools`) and its plot, from the cached run alone."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

from precond.evaluation.cache import JsonCache

matplotlib.use("Agg")
import matplotlib.pyplot as plt

TOOLS_HEADING = "## Tool-calling agents: guarding tau-bench airline calls"
READ_RULE = "read before write"
READING = Path(__file__).with_name("tools_reading.md")
"""The reading of the numbers, written by a person (like next_action_choice.md): rerun, reread."""


def _share(part: int, whole: int) -> str:
    return f"{part}/{whole} ({part / whole:.0%})" if whole else "0/0"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join([*lines, *("| " + " | ".join(r) + " |" for r in rows)]) + "\n"


def _read_learned(summary: dict[str, Any]) -> str:
    learned = summary["per_rule"][READ_RULE]["learned"]
    return f"{sum(bool(v) for v in learned.values())}/{len(learned)}"


def config_table(configs: Sequence[dict[str, Any]]) -> str:
    rows = []
    for c in configs:
        s, cf = c["summary"], c["summary"]["counterfactual"]
        rows.append([f"`{c['config']}`", _read_learned(s), _share(s["refused_breaking"], s["breaking"]),
                     _share(s["allowed_keeping"], s["keeping"]),
                     f"{cf['stopped_at_first_breaking_call']}/{cf['runs_with_a_breaking_call']}",
                     f"{cf['successful_runs_interrupted']}/{cf['successful_runs_with_writes']}",
                     f"{c['seconds']:.1f}"])
    return _table(["ranking/tolerance", "read-before-write learned (writes)", "breaking calls refused",
                   "keeping calls allowed", "runs stopped at their first breaking call",
                   "successful runs interrupted", "infer + judge s"], rows)


def tool_table(summary: dict[str, Any], rules: dict[str, list[str]]) -> str:
    rows = []
    for tool, counts in summary["per_tool"].items():
        learned = "<br>".join(f"`{r}`" for r in rules.get(f"AGENT.{tool}", [])) or "none"
        rows.append([f"`{tool}`", learned, _share(counts["refused_breaking"], counts["breaking"]),
                     _share(counts["allowed_keeping"], counts["keeping"])])
    return _table(["tool", "learned rule", "breaking calls refused", "keeping calls allowed"], rows)


def rule_table(summary: dict[str, Any]) -> str:
    rows = []
    for name, rule in summary["per_rule"].items():
        learned = [t for t, found in rule["learned"].items() if found]
        rows.append([name, ", ".join(f"`{t}`" for t in rule["tools"]),
                     ", ".join(f"`{t}`" for t in learned) or "no",
                     _share(rule["refused_breaking"], rule["breaking"]),
                     _share(rule["allowed_keeping"], rule["keeping"]), rule["words"]])
    return _table(["policy rule (labels)", "tools", "learned for", "breaking calls refused",
                   "keeping calls allowed", "the policy's words"], rows)


def tools_plot(result: dict[str, Any], img: Path) -> Path | None:
    """Per tool, the chosen configuration: breaking calls refused/missed, keeping calls allowed/refused."""
    chosen = next((c for c in result["configs"] if c["config"] == result["chosen"]), None)
    if chosen is None:
        return None
    tools = list(chosen["summary"]["per_tool"])
    counts = [chosen["summary"]["per_tool"][t] for t in tools]
    fig, ax = plt.subplots(figsize=(9, 3.6))
    xs = range(len(tools))
    parts = [("breaking, refused", [c["refused_breaking"] for c in counts], -0.2, 0),
             ("breaking, allowed (missed)", [c["breaking"] - c["refused_breaking"] for c in counts], -0.2, 1),
             ("keeping, allowed", [c["allowed_keeping"] for c in counts], 0.2, 0),
             ("keeping, refused (false alarm)", [c["keeping"] - c["allowed_keeping"] for c in counts], 0.2, 1)]
    for label, values, offset, stacked in parts:
        bottom = [c["refused_breaking"] if offset < 0 else c["allowed_keeping"] for c in counts] if stacked else None
        ax.bar([x + offset for x in xs], values, 0.38, bottom=bottom, label=label)
    ax.set_xticks(list(xs), tools, rotation=20, fontsize=7, ha="right")
    ax.set_ylabel("state-changing calls")
    ax.set_title(f"tau-bench airline, all 120 runs, rules from the 53 successful ones (`{result['chosen']}`)",
                 fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = img / "tools_guard.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def tools_section(result: dict[str, Any], plot: Path | None) -> str:
    chosen = next(c for c in result["configs"] if c["config"] == result["chosen"])
    s = chosen["summary"]
    parts = [
        TOOLS_HEADING + "\n",
        f"`precond eval tools` (precond/evaluation/tools.py): the {result['trajectories']} development trajectories of "
        f"`tau-airline/` converted by `precond convert openai` in {result['convert_s']:.2f} s; rules inferred "
        f"model-free (`enumerate`) from the {result['demonstrations']} successful runs (reward 1) for the six "
        "state-changing tools; then every state-changing call of every run judged by those rules on the history "
        f"before it ({s['calls']} calls) and compared with labels written from `policy.md` for the rules that "
        "calls and results alone decide (the rule table quotes the policy; rules that need the user's words "
        "are not labeled). A call *breaks* the policy when any labeled rule says so. Labels never reach the "
        "request: the demonstrations are the programs, nothing else.\n",
        "Configurations (evidence weighting and ranking; `tolerance=0` is the paper's strict validation):\n",
        config_table(result["configs"]),
        f"The chosen configuration, `{result['chosen']}` (the most breaking calls refused while allowing at least "
        "95% of the keeping ones, on this development data), per tool:\n",
        tool_table(s, chosen["rules"]),
        "Per policy rule (a call counts under each rule that decides it):\n",
        rule_table(s),
    ]
    if plot is not None:
        parts.append(f"![{plot.stem}](img/{plot.name})\n")
    if READING.exists():
        parts.append(READING.read_text(encoding="utf-8"))
    return "\n".join(parts)


def write_tools_section(store: JsonCache, out: Path) -> None:
    """Replace (or add, before `## Speed`) the tool-calling section of the report, and its plot."""
    result = store.get("results", "tools")
    if result is None:
        return
    img = out.parent / "img"
    img.mkdir(parents=True, exist_ok=True)
    section = tools_section(result, tools_plot(result, img)).rstrip() + "\n"
    text = out.read_text(encoding="utf-8") if out.exists() else "# Evaluation results\n"
    start = text.find(TOOLS_HEADING)
    if start >= 0:
        end = text.find("\n## ", start + len(TOOLS_HEADING))
        text = text[:start] + section + (text[end:] if end >= 0 else "")
    else:
        at = text.find("\n## Speed")
        at = len(text) if at < 0 else at + 1
        text = text[:at] + section + "\n" + text[at:]
    out.write_text(text, encoding="utf-8")
