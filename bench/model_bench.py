"""Throughput of the code-model backend on this machine, and how many samples fit the engine's time budget.

Measures, with the real embedded model: load time (cold GGUF conversion into a scratch cache, then warm),
prefill tokens/s over a ~700-token prefix, decode tokens/s at several batch sizes, each in bfloat16 and
float32; then one SGD domain end to end through `CodeModel.complete` (the engine's prompts: one
demonstration, the observation class, each system action's `def` ending in `assert`), from which it derives
the sample budget for 60 s.

    python bench/model_bench.py --threads 1 [--skip-cold] [--json out.json]
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from engine.models import CodeModel, ModelSettings, Sampling, load_code_model
from engine.models.backend import PREFILL_CHUNK
from engine.models.kvcache import growing_cache
from engine.prompting import inference_prefix, inference_suffix
from engine.spec import parse_spec, resolve_actions
from evaluation.settings import data_path

logger = logging.getLogger("model_bench")

PREFIX_TOKENS = 700
DECODE_STEPS = 16


def timed(action: Callable[[], Any]) -> tuple[float, Any]:
    start = time.perf_counter()
    result = action()
    return time.perf_counter() - start, result


def domain_prompts(demos: int) -> tuple[str, list[str]]:
    """The engine's prompt for Restaurants_1: spec and demonstrations only, never the `gt_*` fields."""
    data = json.loads(data_path("sgd", "Restaurants_1.json").read_text())
    spec = parse_spec(data["spec_program"])
    actions = resolve_actions(spec, None)
    prefix = inference_prefix(spec, actions, [demo["program"] for demo in data["demos"][:demos]])
    return prefix, [inference_suffix(spec, action) for action in actions]


def prefix_ids(model: CodeModel) -> list[int]:
    """A real ~700-token prefix: enough demonstrations, then cut to length."""
    prefix, _ = domain_prompts(demos=3)
    ids: list[int] = model.tokenizer(prefix)["input_ids"]
    return ids[:PREFIX_TOKENS]


def prefill(model: CodeModel, ids: list[int]) -> Any:
    """The prefix cache, computed in the backend's chunks."""
    cache = growing_cache(model.model.config)
    with torch.inference_mode():
        for start in range(0, len(ids), PREFILL_CHUNK):
            end = min(start + PREFILL_CHUNK, len(ids))
            model.model(
                input_ids=torch.tensor([ids[start:end]]),
                attention_mask=torch.ones(1, end, dtype=torch.long),
                position_ids=torch.arange(start, end)[None],
                past_key_values=cache,
                use_cache=True,
                logits_to_keep=1,
            )
    return cache


def decode_rate(model: CodeModel, cache: Any, context: int, batch: int) -> float:
    """Generated tokens/s of `batch` rows decoding after the prefix (greedy tokens, fixed step count)."""
    cache = copy.deepcopy(cache)
    cache.batch_repeat_interleave(batch)
    tokens = torch.zeros(batch, 1, dtype=torch.long)
    with torch.inference_mode():
        start = time.perf_counter()
        for step in range(DECODE_STEPS):
            out = model.model(
                input_ids=tokens,
                attention_mask=torch.ones(batch, context + step + 1, dtype=torch.long),
                position_ids=torch.full((batch, 1), context + step),
                past_key_values=cache,
                use_cache=True,
                logits_to_keep=1,
            )
            tokens = out.logits[:, -1].argmax(-1, keepdim=True)
        elapsed = time.perf_counter() - start
    return batch * DECODE_STEPS / elapsed


def bench_dtype(settings: ModelSettings, batches: list[int]) -> tuple[CodeModel, dict[str, Any]]:
    load_s, model = timed(lambda: load_code_model(settings))
    ids = prefix_ids(model)
    prefill(model, ids[:PREFILL_CHUNK])  # warm-up: first calls allocate and pick kernels
    prefill_s, cache = timed(lambda: prefill(model, ids))
    result: dict[str, Any] = {
        "warm_load_s": round(load_s, 2),
        "prefill_tokens": len(ids),
        "prefill_tok_s": round(len(ids) / prefill_s, 1),
        "decode_tok_s": {str(b): round(decode_rate(model, cache, len(ids), b), 1) for b in batches},
    }
    logger.info("%s: %s", settings.dtype, result)
    return model, result


def bench_domain(model: CodeModel, samples: list[int], max_new_tokens: int) -> list[dict[str, Any]]:
    """One domain end to end: all actions' completions with n samples each, as the engine asks for them."""
    prefix, suffixes = domain_prompts(demos=1)
    runs = []
    for n in samples:
        model._prefix = type(model._prefix)()  # cold prefix cache: each run pays its own prefill
        sampling = Sampling(max_new_tokens=max_new_tokens, seed=n)
        wall_s, result = timed(lambda n=n, s=sampling: model.complete(prefix, suffixes, n, s, "statement"))
        texts = [text for texts in result for text in texts]
        new_tokens = [len(model.tokenizer(text)["input_ids"]) for text in texts]
        runs.append(
            {
                "prompts": len(suffixes),
                "samples": n,
                "wall_s": round(wall_s, 2),
                "mean_new_tokens": round(statistics.mean(new_tokens), 1),
                "prefix_tokens": len(model.tokenizer(prefix)["input_ids"]),
            }
        )
        logger.info("domain: %s", runs[-1])
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--skip-cold", action="store_true", help="skip the ~1 min cold conversion")
    parser.add_argument("--dtypes", nargs="+", default=["bfloat16", "float32"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 8, 32])
    parser.add_argument("--samples", nargs="+", type=int, default=[1, 4, 8])
    parser.add_argument("--max-batch", type=int, default=ModelSettings().max_batch)
    parser.add_argument("--max-new-tokens", type=int, default=48)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(args.threads)

    report: dict[str, Any] = {"threads": args.threads, "torch": torch.__version__}
    if not args.skip_cold:
        with tempfile.TemporaryDirectory() as scratch:
            settings = ModelSettings(cache_dir=Path(scratch), threads=args.threads)
            report["cold_load_s"], _ = timed(lambda: load_code_model(settings))
            logger.info("cold load (convert + load): %.1f s", report["cold_load_s"])
    models = {}
    for dtype in args.dtypes:
        settings = ModelSettings(dtype=dtype, threads=args.threads, max_batch=args.max_batch)
        models[dtype], report[dtype] = bench_dtype(settings, args.batches)
    fastest = max(args.dtypes, key=lambda d: float(report[d]["decode_tok_s"][str(max(args.batches))]))
    report["domain_dtype"] = fastest
    report["domain"] = bench_domain(models[fastest], args.samples, args.max_new_tokens)
    per_row = [run["wall_s"] / (run["prompts"] * run["samples"]) for run in report["domain"]]
    largest = report["domain"][-1]
    report["rows_in_60_s_at_largest_n"] = int(60 / per_row[-1])
    report["samples_per_action_in_60_s"] = int(60 / per_row[-1] / largest["prompts"])
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
