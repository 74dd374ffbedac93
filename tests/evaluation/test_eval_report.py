"""Results from separate runs merge; a failed re-run never hides an earlier measurement; the sized next-action table."""

from __future__ import annotations

from pathlib import Path

from precond.evaluation.cache import JsonCache
from precond.evaluation.report import main_table, store_precondition_results

GOOD = {"config": "model/recency", "domain": "Buses_1", "benchmark": "sgd", "error": None,
        "macro": {"precision": 0.9, "recall": 0.5, "f1": 0.6}}
FAILED = {"config": "model/recency", "domain": "Buses_1", "benchmark": "sgd", "error": "model_unavailable: no"}


def test_failed_rerun_keeps_the_measurement(tmp_path: Path) -> None:
    store = JsonCache(tmp_path)
    store_precondition_results(store, {"rows": [GOOD]})
    store_precondition_results(store, {"rows": [FAILED]})
    rows = store.get("results", "preconditions")["rows"]
    assert rows == [GOOD]
    assert "| `model/recency` | 0.900 | 0.500 | 0.600 |" in main_table(rows)


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
