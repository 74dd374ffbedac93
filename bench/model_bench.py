"""The code model's speed on this machine, side by side in one run: the backend in each dtype and thread
count, and llama.cpp on the same GGUF and prompt when `llama_cpp` is importable.

For each configuration, in a fresh process (so its memory is its own): load time, resident memory after load
and at peak, prefill tokens/s of a real ~1,000-token domain prompt (the backend's chunked path, as the engine
runs it), decode tokens/s at batch 1, and the wall time of 8 samples x 48 tokens of that prompt (one prefill,
then 8 rows decoded together; llama.cpp decodes them one after another from a saved state). Each figure is
the best of `--repeat` runs: on a shared machine the slowest runs measure the neighbours. Optionally
(`--domain`) one SGD domain through `CodeModel.complete` with the engine's prompts, in the dtype `auto` picks.

    python bench/model_bench.py [--threads 1 2] [--dtypes float32 bfloat16] [--repeat 3] [--domain] [--json f]
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import logging
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from precond.engine.candidates.prompting import inference_prefix, inference_suffix
from precond.engine.models import CodeModel, ModelSettings, Sampling, load_code_model
from precond.engine.models.kvcache import growing_cache
from precond.engine.models.prefixes import Prefix, PrefixStore
from precond.engine.models.weights import choose_dtype
from precond.engine.spec import parse_spec, resolve_actions
from precond.evaluation.report import cpu_model
from precond.evaluation.settings import data_path

logger = logging.getLogger("model_bench")

PROMPT_TOKENS = 1024
DECODE_STEPS = 32
SAMPLES = 8
SAMPLE_TOKENS = 48
LLAMA_CPP_MISSING = (
    "llama.cpp: skipped (the `llama_cpp` module is not importable; `pip install llama-cpp-python` builds "
    "it from source, ~30 min on 2 cores)"
)


def timed(action: Callable[[], Any]) -> tuple[float, Any]:
    start = time.perf_counter()
    result = action()
    return time.perf_counter() - start, result


def best(repeat: int, action: Callable[[], Any]) -> float:
    return min(timed(action)[0] for _ in range(repeat))


def rss_mb() -> dict[str, int]:
    """Resident memory now and at peak, from /proc (Linux)."""
    fields = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines() if ":" in line)
    return {
        "rss_mb": int(fields["VmRSS"].split()[0]) // 1024,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024,
    }


def domain_prompts(demos: int) -> tuple[str, list[str]]:
    """The engine's prompt for Restaurants_1: spec and demonstrations only, never the `gt_*` fields."""
    data = json.loads(data_path("sgd", "Restaurants_1.json").read_text())
    spec = parse_spec(data["spec_program"])
    actions = resolve_actions(spec, None)
    prefix = inference_prefix(spec, actions, [demo["program"] for demo in data["demos"][:demos]])
    return prefix, [inference_suffix(spec, action) for action in actions]


def prompt_text(tokens: int, count: Callable[[str], list[int]]) -> str:
    """A real domain prompt (enough demonstrations) cut to about `tokens` tokens at a line end."""
    prefix, suffixes = domain_prompts(demos=4)
    text = prefix + suffixes[0]
    ids = count(text)
    if len(ids) <= tokens:
        return text
    lines, kept = text.splitlines(keepends=True), ""
    for line in lines:
        if len(count(kept + line)) > tokens:
            break
        kept += line
    return kept


# --- the backend (transformers + torch) ---


def cold(model: CodeModel) -> None:
    """Forget every kept prefix: each run pays its own prefill."""
    model._prefixes = PrefixStore(model._prefixes.max_bytes)


def backend_prefill(model: CodeModel, ids: list[int]) -> Prefix:
    """The engine's own prefill (chunked, into its growing cache), from nothing."""
    cold(model)
    with torch.inference_mode():
        return model._prefix_cache(tuple(ids))


def backend_decode(model: CodeModel, prefix: Prefix, batch: int, steps: int) -> None:
    """`batch` rows continue the prefix for `steps` greedy tokens (a fixed amount of work: no stopping), as the
    engine's rows do: the prefix's cache read by all of them (`head`), each row's own tokens in its own cache."""
    cache = growing_cache(model.model.config)
    context = len(prefix.tokens)
    tokens = torch.full((batch, 1), prefix.tokens[-1], dtype=torch.long)
    with torch.inference_mode():
        for step in range(steps):
            out = model.model(
                input_ids=tokens,
                attention_mask=torch.ones(batch, step + 1, dtype=torch.long),
                position_ids=torch.full((batch, 1), context + step),
                cache=cache,
                use_cache=True,
                logits_to_keep=1,
                head=prefix.cache,
            )
            tokens = out.logits[:, -1].argmax(-1, keepdim=True)


def bench_backend(dtype: str, quant: str, threads: int, repeat: int) -> dict[str, Any]:
    settings = ModelSettings(dtype=dtype, quant=quant, threads=threads)
    load_s, model = timed(lambda: load_code_model(settings))
    loaded = rss_mb()
    ids: list[int] = model.tokenizer(prompt_text(PROMPT_TOKENS, lambda t: model.tokenizer(t)["input_ids"]))[
        "input_ids"
    ]
    backend_prefill(model, ids[:256])  # warm-up: first calls allocate and pick kernels
    prefill_s = best(repeat, lambda: backend_prefill(model, ids))
    prefix = backend_prefill(model, ids)
    decode_s = best(repeat, lambda: backend_decode(model, prefix, 1, DECODE_STEPS))

    def samples() -> None:
        backend_decode(model, backend_prefill(model, ids), SAMPLES, SAMPLE_TOKENS)

    samples_s = best(repeat, samples)
    return {
        "engine": "backend",
        "dtype": model.info.dtype,
        "quant": model.info.quant,
        "threads": threads,
        "load_s": round(load_s, 2),
        "prompt_tokens": len(ids),
        "prefill_tok_s": round(len(ids) / prefill_s, 1),
        "decode_b1_tok_s": round(DECODE_STEPS / decode_s, 1),
        f"samples_{SAMPLES}x{SAMPLE_TOKENS}_s": round(samples_s, 2),
        "loaded_rss_mb": loaded["rss_mb"],
        **rss_mb(),
    }


# --- llama.cpp on the same GGUF (only where llama_cpp is installed) ---


def embedded_gguf(directory: Path) -> Path:
    from precond.engine.models.store import EMBEDDED_NAME, EMBEDDED_SHA256, find_embedded_parts, join_parts

    target = directory / f"{EMBEDDED_NAME}.gguf"
    join_parts(find_embedded_parts(), target, EMBEDDED_SHA256)
    return target


def bench_llama_cpp(threads: int, repeat: int) -> dict[str, Any]:
    import llama_cpp

    with tempfile.TemporaryDirectory() as scratch:
        gguf = embedded_gguf(Path(scratch))
        load_s, llm = timed(
            lambda: llama_cpp.Llama(
                model_path=str(gguf), n_ctx=PROMPT_TOKENS + 256, n_threads=threads, n_threads_batch=threads,
                n_batch=512, verbose=False,
            )
        )
        loaded = rss_mb()
        ids = llm.tokenize(prompt_text(PROMPT_TOKENS, lambda t: llm.tokenize(t.encode())).encode())

        def prefill() -> None:
            llm.reset()
            llm.eval(ids)

        def decode(steps: int) -> None:
            for _ in range(steps):
                llm.eval([ids[-1]])

        prefill()
        prefill_s = best(repeat, prefill)
        state = llm.save_state()
        def decode_from_prompt() -> None:
            llm.load_state(state)
            decode(DECODE_STEPS)

        decode_s = best(repeat, decode_from_prompt)

        def samples() -> None:
            prefill()
            saved = llm.save_state()
            for _ in range(SAMPLES):
                llm.load_state(saved)
                decode(SAMPLE_TOKENS)

        samples_s = best(repeat, samples)
    return {
        "engine": f"llama.cpp {getattr(llama_cpp, '__version__', '?')}",
        "dtype": "Q4_K_M (the GGUF as shipped)",
        "quant": "Q4_K_M",
        "threads": threads,
        "load_s": round(load_s, 2),
        "prompt_tokens": len(ids),
        "prefill_tok_s": round(len(ids) / prefill_s, 1),
        "decode_b1_tok_s": round(DECODE_STEPS / decode_s, 1),
        f"samples_{SAMPLES}x{SAMPLE_TOKENS}_s": round(samples_s, 2),
        "loaded_rss_mb": loaded["rss_mb"],
        **rss_mb(),
    }


# --- one domain through the engine's completion call ---


def bench_domain(threads: int, samples: list[int], max_new_tokens: int) -> dict[str, Any]:
    """One domain end to end: all actions' completions with n samples each, as the engine asks for them."""
    model = load_code_model(ModelSettings(threads=threads))
    prefix, suffixes = domain_prompts(demos=1)
    runs = []
    for n in samples:
        cold(model)
        sampling = Sampling(max_new_tokens=max_new_tokens, seed=n)
        wall_s, result = timed(functools.partial(model.complete, prefix, suffixes, n, sampling, "statement"))
        texts = [text for texts in result for text in texts]
        runs.append(
            {
                "prompts": len(suffixes),
                "samples": n,
                "wall_s": round(wall_s, 2),
                "mean_new_tokens": round(statistics.mean(len(model.tokenizer(t)["input_ids"]) for t in texts), 1),
                "prefix_tokens": len(model.tokenizer(prefix)["input_ids"]),
            }
        )
        logger.info("domain: %s", runs[-1])
    return {"dtype": model.info.dtype, "dtype_reason": model.info.dtype_reason, "threads": threads, "runs": runs}


def child(argv: list[str]) -> dict[str, Any]:
    """One configuration, run in this (fresh) process: `backend DTYPE QUANT THREADS REPEAT`, `llama_cpp ...`."""
    kind, *rest = argv
    threads = int(rest[-2])
    torch.set_num_threads(threads)
    if kind == "backend":
        return bench_backend(rest[0], rest[1], threads, int(rest[-1]))
    if kind == "llama_cpp":
        return bench_llama_cpp(threads, int(rest[-1]))
    raise ValueError(f"unknown configuration {kind!r}")


def run_child(argv: list[str], script: str = __file__, threads: str | None = None) -> dict[str, Any]:
    """One configuration of `script` (`--child ARGV`) in a fresh process, so its memory and caches are its own;
    the result is the last line it prints, with the load average before and after (a shared machine's noise)."""
    threads = threads or argv[-2]
    env = {**os.environ, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads, "TOKENIZERS_PARALLELISM": "false"}
    before = os.getloadavg()[0]
    done = subprocess.run(
        [sys.executable, script, "--child", *argv], env=env, capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise RuntimeError(f"{argv} failed:\n{done.stderr[-3000:]}")
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    result["load_average"] = [round(before, 2), round(os.getloadavg()[0], 2)]
    logger.info("%s", json.dumps(result))
    return result


def report_rows(rows: list[dict[str, Any]], path: Path | None) -> None:
    """Print the rows with the machine they ran on, and keep them at `path` when given."""
    report = {"cpu": cpu_model(), "cores": os.cpu_count(), "rows": rows}
    if path:
        path.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


def split_values(values: list[str]) -> list[str]:
    """`--quants none int8` and `--quants none,int8` alike."""
    return [value for given in values for value in given.split(",") if value]


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--dtypes", nargs="+", default=["float32", "bfloat16"])
    parser.add_argument("--quants", nargs="+", default=["none", "int8"], help="MODEL_QUANT values (int8: where the "
                        "CPU runs it), `none int8` or `none,int8`")
    parser.add_argument("--rounds", type=int, default=1, help="run every configuration this many times, "
                        "interleaved (old and new side by side on a shared machine)")
    parser.add_argument("--repeat", type=int, default=3, help="each figure is the best of this many runs")
    parser.add_argument("--no-llama-cpp", action="store_true")
    parser.add_argument("--domain", action="store_true", help="also one SGD domain through CodeModel.complete")
    parser.add_argument("--samples", nargs="+", type=int, default=[4, 8])
    parser.add_argument("--max-new-tokens", type=int, default=48)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child)))
        return
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    auto = choose_dtype("auto", torch.device("cpu"))
    report: dict[str, Any] = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "auto_dtype": [str(auto[0]).removeprefix("torch."), auto[1]],
        "repeat": args.repeat,
        "results": [],
    }
    for _ in range(args.rounds):
        for threads in args.threads:
            for dtype in args.dtypes:
                for quant in split_values(args.quants):
                    report["results"].append(run_child(["backend", dtype, quant, str(threads), str(args.repeat)]))
            if args.no_llama_cpp:
                continue
            if importlib.util.find_spec("llama_cpp") is None:
                logger.info(LLAMA_CPP_MISSING)
                report["llama_cpp"] = LLAMA_CPP_MISSING
                continue
            report["results"].append(run_child(["llama_cpp", str(threads), str(args.repeat)]))
    if args.domain:
        torch.set_num_threads(max(args.threads))
        report["domain"] = bench_domain(max(args.threads), args.samples, args.max_new_tokens)
    print(json.dumps(report, indent=2))
    print(markdown_table(report["results"]))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


def markdown_table(results: list[dict[str, Any]]) -> str:
    key = f"samples_{SAMPLES}x{SAMPLE_TOKENS}_s"
    lines = [
        f"| engine | dtype | quant | threads | prefill tok/s | decode tok/s (batch 1) | {SAMPLES} x {SAMPLE_TOKENS} s "
        "| load s | RSS after load MB | peak RSS MB | load avg (before, after) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['engine']} | {r['dtype']} | {r['quant']} | {r['threads']} | {r['prefill_tok_s']} "
            f"| {r['decode_b1_tok_s']} "
            f"| {r[key]} | {r['load_s']} | {r['loaded_rss_mb']} | {r['peak_rss_mb']} "
            f"| {r['load_average'][0]}, {r['load_average'][1]} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
