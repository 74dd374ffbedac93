"""The same pipeline on each runtime, side by side in one run: one SGD domain's default inference end to end,
and next-action latency (p50/p95), with the project's backend and with llama.cpp on the same GGUF.

Only the code model changes between rows: the engine, its prompts, the sandbox and the request are the same.
llama.cpp is reached through `LlamaCppModel`, an adapter with the backend's `complete`: llama-cpp-python has no
batched sampling, so the n samples of a prompt are decoded one after another, each reusing the prompt's
evaluated tokens (its prefix match), which is the fair way to run it. It is a benchmark adapter, not a serving
backend (a second backend would be worth its upkeep only if it won by a wide margin).

Each configuration runs in a fresh process, one after another; take timings with nothing else running.

    python bench/pipeline_bench.py [--domain Restaurants_1] [--turns 20] [--threads 2] [--runtimes backend] [--json f]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import resource
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # `bench.model_bench` when run as `python bench/pipeline_bench.py`

from precond.engine.engine import Engine  # noqa: E402
from precond.engine.models.stopping import StopRule, stop_index  # noqa: E402
from precond.engine.settings import ModelSettings, SandboxSettings  # noqa: E402
from precond.evaluation.settings import data_path  # noqa: E402
from precond_client.schemas import (  # noqa: E402
    InferRequest,
    ModelInfo,
    NextActionMode,
    NextActionOptions,
    NextActionRequest,
)

logger = logging.getLogger("pipeline_bench")

RUNTIMES = ("backend", "llama_cpp")

NEXT_MODES: tuple[NextActionMode, ...] = ("constrained", "sample")
"""Next-action modes timed: the default (the model scores every allowed call) and the paper's Algorithm 1 (a greedy
line, verified), the one llama.cpp can run (`LlamaCppModel`)."""


class LlamaCppModel:
    """`CodeModel.complete` on llama.cpp: rows one after another, each reusing the prompt's evaluated tokens.
    It has no `score` (llama-cpp-python keeps one position's logits unless it keeps every position's, 5 GB at
    this context), so its next actions run the paper's sampling mode only."""

    known_calls: tuple[str, ...] = ()

    def __init__(self, gguf: Path, threads: int, n_ctx: int = 8192) -> None:
        import llama_cpp

        self.llm = llama_cpp.Llama(model_path=str(gguf), n_ctx=n_ctx, n_threads=threads, n_threads_batch=threads,
                                   n_batch=512, verbose=False)
        self.info = ModelInfo(name=f"llama.cpp {llama_cpp.__version__} {gguf.name}", device="cpu",
                              dtype="Q4_K_M", dtype_reason="the GGUF as shipped")

    def complete(self, prefix: str, suffixes: Sequence[str], n: int, sampling: Any, stop: StopRule,
                 should_stop: Callable[[], bool] | None = None) -> list[list[str]]:
        rows = 1 if sampling.greedy else n
        results: list[list[str]] = []
        for suffix in suffixes:
            texts = []
            for row in range(rows):
                out: Any = self.llm.create_completion(
                    prefix + suffix, max_tokens=sampling.max_new_tokens, temperature=sampling.temperature,
                    top_p=sampling.top_p, seed=sampling.seed + row, stop=["\n"] if stop == "line" else None,
                )
                text: str = out["choices"][0]["text"]
                cut = stop_index(text, stop)
                texts.append(text if cut is None else text[:cut])
            results.append(texts)
        return results


def domain(name: str) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((data_path() / "sgd" / f"{name}.json").read_text())
    return data


def histories(data: dict[str, Any], turns: int) -> list[str]:
    """Histories that end just before a system act, across the test dialogs: what a dialog system sends."""
    found: list[str] = []
    for dialog in data["test"]:
        lines = dialog["program"].splitlines()
        for i, line in enumerate(lines):
            if line.startswith("system.") and not lines[i - 1].startswith("system.") and i > 2:
                found.append("\n".join(lines[:i]) + "\n")
                if len(found) == turns:
                    return found
    return found


def run(runtime: str, dtype: str, quant: str, threads: int, name: str, turns: int) -> dict[str, Any]:
    """One row, in this process: the domain's default inference, then `turns` next-action requests."""
    import torch

    torch.set_num_threads(threads)
    data = domain(name)
    demos = [d["program"] for d in data["demos"]]
    with tempfile.TemporaryDirectory() as scratch:
        if runtime == "llama_cpp":
            from bench.model_bench import embedded_gguf

            gguf = embedded_gguf(Path(scratch))
            loader: Callable[[], Any] = lambda: LlamaCppModel(gguf, threads)  # noqa: E731
        else:
            from precond.engine.models import load_code_model

            loader = lambda: load_code_model(ModelSettings(dtype=dtype, quant=quant, threads=threads))  # noqa: E731
        with SandboxSettings().build() as sandbox:
            engine = Engine(sandbox, loader)
            load_s, _ = timed(engine.model)
            load_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024
            infer_s, inferred = timed(lambda: engine.infer(InferRequest(spec=data["spec_program"],
                                                                        demonstrations=demos)))
            latencies: dict[str, list[float]] = {}
            for mode in NEXT_MODES if runtime == "backend" else NEXT_MODES[1:]:
                for history in histories(data, turns):
                    request = NextActionRequest(spec=data["spec_program"], preconditions=inferred.preconditions,
                                                demonstrations=demos[:1], history=history,
                                                options=NextActionOptions(mode=mode))
                    start = time.perf_counter()
                    engine.next_action(request)
                    latencies.setdefault(mode, []).append(time.perf_counter() - start)
    return {
        "runtime": runtime, "dtype": getattr(engine.model().info, "dtype", dtype),
        "quant": getattr(engine.model().info, "quant", quant), "threads": threads,
        "domain": name, "load_s": round(load_s, 1), "infer_s": round(infer_s, 1),
        "infer_generate_s": inferred.stats.seconds.get("generate"),
        **{f"next_action_{mode}_{name}_s": value for mode, times in latencies.items()
           for name, value in percentiles(times).items()},
        "requests": turns,
        "load_peak_rss_mb": load_peak,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024,
    }


def percentiles(times: Sequence[float]) -> dict[str, float]:
    return {"p50": round(statistics.median(times), 2),
            "p95": round(sorted(times)[max(0, round(0.95 * len(times)) - 1)], 2)}


def timed(action: Callable[[], Any]) -> tuple[float, Any]:
    start = time.perf_counter()
    result = action()
    return time.perf_counter() - start, result


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--domain", default="Restaurants_1")
    parser.add_argument("--turns", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--dtypes", nargs="+", default=["auto"])
    parser.add_argument("--quants", nargs="+", default=["auto"], help="MODEL_QUANT values, each beside each dtype "
                        "(`none int8` or `none,int8`)")
    parser.add_argument("--rounds", type=int, default=1, help="every configuration this many times, interleaved")
    parser.add_argument("--runtimes", nargs="+", choices=RUNTIMES, default=list(RUNTIMES),
                        help="which runtimes get a row (llama_cpp only where llama_cpp is importable)")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--child", nargs=6, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        runtime, dtype, quant, threads, name, turns = args.child
        print(json.dumps(run(runtime, dtype, quant, int(threads), name, int(turns))))
        return
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from bench.model_bench import report_rows, run_child, split_values

    threads = str(args.threads)
    rows = [run_child(["backend", dtype, quant, threads, args.domain, str(args.turns)], __file__, threads)
            for _ in range(args.rounds) for dtype in args.dtypes for quant in split_values(args.quants)
            if "backend" in args.runtimes]
    if "llama_cpp" not in args.runtimes:
        logger.info("llama.cpp: skipped (--runtimes)")
    elif importlib.util.find_spec("llama_cpp") is not None:
        rows.append(run_child(["llama_cpp", "-", "-", threads, args.domain, str(args.turns)], __file__, threads))
    else:
        logger.info("llama.cpp: skipped (llama_cpp is not importable)")
    report_rows(rows, args.json)


if __name__ == "__main__":
    main()
