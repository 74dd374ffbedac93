"""Results from separate runs merge; a failed re-run never hides an earlier measurement; the sized next-action table;
the report is one current section per benchmark, in the layout's order, each naming the command that regenerates
it, with no superseded tables."""

from __future__ import annotations

from pathlib import Path

from precond.evaluation.cache import JsonCache
from precond.evaluation.report import precondition_table, store_precondition_results

GOOD = {"config": "model/recency", "domain": "Buses_1", "benchmark": "sgd", "error": None,
        "macro": {"precision": 0.9, "recall": 0.5, "f1": 0.6}}
FAILED = {"config": "model/recency", "domain": "Buses_1", "benchmark": "sgd", "error": "model_unavailable: no"}


def test_failed_rerun_keeps_the_measurement(tmp_path: Path) -> None:
    store = JsonCache(tmp_path)
    store_precondition_results(store, {"rows": [GOOD]})
    store_precondition_results(store, {"rows": [FAILED]})
    stored = store.get("results", "preconditions")
    assert stored is not None
    assert stored["rows"] == [GOOD]
    assert "| model/recency | sgd | 1 | 0.900 | 0.500 | 0.600 |" in precondition_table(stored["summary"])


def test_sized_run_is_a_table_with_intervals_and_a_plot(tmp_path: Path) -> None:
    from precond.evaluation.plots import sized_plot
    from precond.evaluation.report import sized_table
    from precond.evaluation.sized import summarize

    row = {"turn": 1, "reference": ["x()"], "seconds": 1.0, "domain": "D"}
    results = {"base": [row | {"dialog": d, "predicted": ["y()"], "compatible": [False]} for d in "abc"],
               "mode": [row | {"dialog": d, "predicted": ["x()"], "compatible": [True]} for d in "abc"]}
    rows = summarize(results, "base")
    table = sized_table({"rows": rows})
    assert "| `mode` | 3 | 3 | 1.000 [1.000, 1.000] | 1.000 [1.000, 1.000] (n=3) | +1.000 [+1.000, +1.000]" in table
    plot = sized_plot(rows, tmp_path)
    assert plot is not None and plot.stat().st_size > 0


def test_the_next_action_section_is_replaced_in_place_and_the_rest_kept(tmp_path: Path) -> None:
    from precond.evaluation.report import NEXT_ACTION_HEADING, write_next_action_section

    store = JsonCache(tmp_path / "cache")
    out = tmp_path / "results.md"
    out.write_text("# Evaluation results\n\n## Policy\n\nold policy\n\n## Speed\n\nfast\n", encoding="utf-8")
    write_next_action_section(store, out)
    first = out.read_text(encoding="utf-8")
    assert first.index("## Policy") < first.index(NEXT_ACTION_HEADING) < first.index("## Speed")
    assert "No sized next-action run cached yet" in first and "fast" in first and "old policy" in first
    store.put({"rows": [], "inferred_from": "enumerate/recency", "turns_per_domain": 100, "seed": 0},
              "results", "next-action")
    write_next_action_section(store, out)
    second = out.read_text(encoding="utf-8")
    assert second.count(NEXT_ACTION_HEADING) == 1 and "No sized next-action run" not in second
    assert "at least 100 system turns" in second and second.endswith("## Speed\n\nfast\n")


OLD_REPORT = """# Evaluation results

## Twenty development domains: mean, worst domain, domains at or below `always`

domains table from an earlier run

## Precondition inference (macro over actions; SGD = mean of its 4 domains)

| config | sgd F1 |
|---|---|
| `enumerate/subsumption` | 0.6041 |

## Policy (SGD next-action prediction, the small grid of `precond eval policy`)

superseded grid

## Next action at size: modes compared with intervals

old sized table

### Behaviour cloning (BC) against the prompted policy (Act), each alone and constrained

hand-written BC table

## Tool-calling agents with labelled calls (`precond eval tools --labels`)

hand-written labelled table
"""


def test_the_report_is_one_current_section_per_benchmark_in_order(tmp_path: Path) -> None:
    from precond.evaluation.layout import SECTIONS
    from precond.evaluation.report import write_report

    store = JsonCache(tmp_path / "cache")
    store.put({"rows": [], "inferred_from": "enumerate/recency", "turns_per_domain": 100, "seed": 0},
              "results", "next-action")
    store_precondition_results(store, {"rows": [GOOD | {"seconds": {"rank": 0.5}, "wall_s": 1.0, "n_demos": 10,
                                                         "domain": "Restaurants_1"}]})
    out = tmp_path / "docs" / "results.md"
    out.parent.mkdir()
    out.write_text(OLD_REPORT, encoding="utf-8")
    write_report(store, out, tmp_path / "absent_bench.py")
    text = out.read_text(encoding="utf-8")
    headings = [line for line in text.splitlines() if line.startswith("## ")]
    assert headings == [s.heading for s in SECTIONS]
    assert "superseded grid" not in text and "0.6041" not in text
    assert "domains table from an earlier run" in text  # no run of it cached: kept as it was
    assert "hand-written labelled table" in text
    next_action = text[text.index("## Next action"):text.index("## Tool-calling agents:")]
    assert "at least 100 system turns" in next_action and "old sized table" not in next_action
    assert "hand-written BC table" in next_action  # a subsection the cache does not write is kept
    assert "Regenerate: `precond eval next-action`." in next_action and "How chosen:" in next_action
    speed = text[text.index("## Speed"):text.index("## Defaults chosen")]
    assert "| `model/recency` | 0.50 | 1.0 |" in speed
    transfer = text[text.index("## Prior rules"):]
    assert "No run cached yet (`precond eval transfer`)" in transfer
    write_report(store, out, tmp_path / "absent_bench.py")
    assert out.read_text(encoding="utf-8").split("- generated:")[1].split("\n", 1)[1] == \
        text.split("- generated:")[1].split("\n", 1)[1]  # regenerating changes nothing but the time
