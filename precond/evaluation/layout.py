"""The layout of docs/results.md: one current section per benchmark, in a fixed order, each with the command that
regenerates it and how its configurations were chosen.

A reader wants today's table, so the full report (`precond eval report`) writes only these sections: a section whose
run the cache holds is rewritten from it, keeping the hand-written subsections (`### ...`) it does not generate;
a section whose run the cache lacks stays as the report had it (a run made elsewhere is never wiped), or says which
command fills it. Anything else (an older layout's tables, superseded figures) is dropped: history is in
CHANGELOG.md.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from precond.evaluation.cache import JsonCache


@dataclass(frozen=True)
class Inputs:
    """What a section is built from: the cache, the folder its plots go to, the sandbox benchmark script."""

    store: JsonCache
    img: Path
    bench: Path


Build = Callable[[Inputs], "str | None"]


@dataclass(frozen=True)
class Section:
    heading: str
    regenerate: str
    """The command that fills this section from a new run (written where the section's text does not name it)."""
    chosen: str | None
    """How the configurations of its table were chosen (None where its text or table says it row by row)."""
    build: Build
    """The section from the cache, None when the cache holds no run of it."""


def _domains(at: Inputs) -> str | None:
    from precond.evaluation import generalisation, safety

    rows, counterfactual = at.store.get("results", "domains"), at.store.get("results", "counterfactual")
    if not rows and not counterfactual:
        return None
    parts = [generalisation.section(rows or [])] if rows else [generalisation.HEADING + "\n"]
    if counterfactual:
        parts.append(safety.section(counterfactual, at.img, counterfactual[0]["config"]))
    return "\n".join(parts)


def _noise(at: Inputs) -> str | None:
    from precond.evaluation.report import noise_section
    from precond.evaluation.sweep import collect

    rows = (at.store.get("results", "preconditions") or {"rows": []})["rows"]
    return noise_section(rows, at.img) if collect(rows) else None


def _next_action(at: Inputs) -> str | None:
    from precond.evaluation.plots import sized_plot
    from precond.evaluation.report import next_action_section

    sized = at.store.get("results", "next-action")
    if not sized and not at.store.get("results", "next-action-alfworld"):
        return None
    return next_action_section(at.store, sized_plot(sized["rows"] if sized else [], at.img))


def _tools(at: Inputs) -> str | None:
    from precond.evaluation.tools_report import tools_plot, tools_section

    tools = at.store.get("results", "tools")
    return tools_section(tools, tools_plot(tools, at.img)) if tools else None


def _speed(at: Inputs) -> str | None:
    from precond.evaluation.report import SPEED_DOMAIN, speed_section

    rows = (at.store.get("results", "preconditions") or {"rows": []})["rows"]
    timed = any(r["domain"] == SPEED_DOMAIN and r.get("seconds") for r in rows)
    return speed_section(at.store, at.bench) if timed else None


def _analysis(at: Inputs) -> str | None:
    from precond.evaluation.report import ANALYSIS

    return ANALYSIS.read_text(encoding="utf-8")


def _plots(at: Inputs) -> str | None:
    from precond.evaluation.plots import demos_plot, per_action_plot, sized_plot

    pre = (at.store.get("results", "preconditions") or {"rows": []})["rows"]
    sized = at.store.get("results", "next-action")
    plots = [per_action_plot(pre, at.img), demos_plot(pre, at.img), sized_plot(sized["rows"] if sized else [], at.img)]
    shown = [f"![{p.stem}](img/{p.name})" for p in plots if p is not None]
    return "\n".join(["## Plots\n", *shown, ""]) if shown else None


def _transfer(at: Inputs) -> str | None:
    from precond.evaluation import transfer

    rows = at.store.get("results", "transfer")
    return transfer.section(rows) if rows else None


SECTIONS: tuple[Section, ...] = (
    Section("## Twenty development domains: mean, worst domain, domains at or below `always`",
            'precond eval domains --configs "enumerate/cautious/guard=spec/lib=lodo,always,gt"; '
            "precond eval counterfactual", None, _domains),
    Section("## Noise and sparsity (SGD, `enumerate/recency`)", "precond eval preconditions --configs noise",
            "the model-free default ranking with strict and default tolerance, each setting a fixed share of "
            "injected errors or a number of demonstrations drawn at random (3 seeds)", _noise),
    Section("## Next action at size: modes compared with intervals", "precond eval next-action",
            "each mode against the unconstrained prompt (`none/plain/shots=1`) on the same seeded sample of turns",
            _next_action),
    Section("## Tool-calling agents: guarding tau-bench airline calls", "precond eval tools",
            "the most breaking calls refused while allowing at least 95% of the keeping ones, on the "
            "development trajectories", _tools),
    Section("## Tool-calling agents with labelled calls (`precond eval tools --labels`)",
            "precond eval tools --labels", "the default configuration, without and with the labelled calls",
            lambda _at: None),
    Section("## Speed", "precond eval report", "every configuration the cache holds, on one domain", _speed),
    Section("## Defaults chosen, and what limits the results", "precond eval report",
            "each default by the measurement its paragraph names", _analysis),
    Section("## Plots", "precond eval report", None, _plots),
    Section("## Prior rules from the tenant's other services (leave one domain out)", "precond eval transfer",
            None, _transfer),
)


def split(text: str, level: str = "## ") -> dict[str, str]:
    """The report's sections by heading (each from its heading to the next heading of `level`)."""
    starts = [m.start() for m in re.finditer(rf"^{re.escape(level)}", text, re.MULTILINE)]
    ends = [*starts[1:], len(text)][:len(starts)]
    return {text[s:].split("\n", 1)[0]: text[s:e] for s, e in zip(starts, ends, strict=True)}


def _complete(section: Section, built: str, kept: str | None) -> str:
    """The section built from the cache, its hand-written subsections kept from the report, its command and how
    its configurations were chosen added where its text does not say them."""
    extra = [text for heading, text in split(kept or "", "### ").items() if heading not in built]
    notes = [] if "Regenerate: " in built else [f"Regenerate: `{section.regenerate}`."]
    notes += [f"How chosen: {section.chosen}."] if section.chosen and "How chosen" not in built else []
    head, _, body = built.rstrip().partition("\n")
    lines = [head, *(["", " ".join(notes)] if notes else []), body]
    return "\n".join(lines).rstrip() + "\n\n" + "".join(t.rstrip() + "\n\n" for t in extra)


def sections(at: Inputs, old: str) -> list[str]:
    """Every section of the layout, in its order, from the cache or kept from `old` (the report as it was)."""
    kept = split(old)
    out = []
    for section in SECTIONS:
        built = section.build(at)
        previous = kept.get(section.heading)
        if built is not None:
            out.append(_complete(section, built, previous))
        elif previous is not None:
            out.append(previous.rstrip() + "\n\n")
        else:
            out.append(f"{section.heading}\n\nNo run cached yet (`{section.regenerate}`).\n\n")
    return out
