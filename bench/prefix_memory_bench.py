"""What a serving worker holds when its kept prompt prefixes fill their bound: next-action requests for many
distinct dialogs under several tenants (each a scope of its own, as the queue worker runs jobs), until the
prefix store has had to evict, then a few more; the process's resident memory sampled throughout.

Every dialog is a new prompt (its spec, one demonstration and its own history), so each request keeps one more
prefix until the bound (`MODEL_PREFIX_CACHE_MB`) pushes the least recent out. Preconditions are the domain's
reference set, so no inference runs first. Each bound runs in a fresh process, one after another.

    PRECOND_DATA_DIR=DIR python bench/prefix_memory_bench.py [--bounds-mb 32 768] [--tenants 3] [--after 3]
        [--domains Homes_1 Restaurants_1 Banks_1] [--threads 2] [--quant auto] [--json f] [--progress f]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # `bench.*` when run as `python bench/prefix_memory_bench.py`

from bench.pipeline_bench import domain, histories  # noqa: E402
from precond.engine.engine import Engine  # noqa: E402
from precond.engine.scope import scoped  # noqa: E402
from precond.engine.settings import ModelSettings, SandboxSettings  # noqa: E402
from precond_client.schemas import NextActionRequest  # noqa: E402

logger = logging.getLogger("prefix_memory_bench")

MIB = 1 << 20


def status_mb(field: str) -> int:
    """`VmRSS` (resident now) or `VmHWM` (the kernel's resident peak) of this process, in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) // 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


class Sampler:
    """The largest `VmRSS` seen every few milliseconds: what a call adds at its peak, beside the kernel's `VmHWM`."""

    def __init__(self, every_s: float = 0.002) -> None:
        self.every_s = every_s
        self.peak_mb = 0
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        while not self._done.is_set():
            self.peak_mb = max(self.peak_mb, status_mb("VmRSS"))
            time.sleep(self.every_s)

    def __enter__(self) -> Sampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._thread.join()


def requests(names: list[str], tenants: int) -> Iterator[tuple[str, NextActionRequest]]:
    """(tenant, request) for every dialog of every domain, the domains interleaved and the tenants in turn: one
    history per test dialog, so no prompt extends another."""
    per_domain = []
    for name in names:
        data = domain(name)
        demos = [d["program"] for d in data["demos"]][:1]
        preconditions = {f"SYSTEM.{action}": list(rule) for action, rule in data["gt_preconditions"].items()}
        asks = [NextActionRequest(spec=data["spec_program"], preconditions=preconditions,
                                  demonstrations=demos, history=history)
                for history in one_per_dialog(data)]
        per_domain.append(asks)
    index = 0
    for group in zip(*per_domain, strict=False):
        for request in group:
            yield f"tenant-{index % tenants}", request
            index += 1


def one_per_dialog(data: dict[str, Any]) -> list[str]:
    """The middle one of each test dialog's histories that end just before a system act: a prompt of 1,000-2,000
    tokens with the spec and one demonstration (the last one ends before a goodbye, which the rules decide alone
    in most dialogs, without the model)."""
    return [found[len(found) // 2] for dialog in data["test"]
            if (found := histories({"test": [dialog]}, len(dialog["program"])))]


def run(bound_mb: int, names: list[str], tenants: int, after: int, threads: int, quant: str,
        progress: Path | None) -> dict[str, Any]:
    """One bound, in this process: requests until the store has evicted, then `after` more; with `progress`, a
    line per request there (what a slow run has shown so far, should it be stopped)."""
    import torch

    from precond.engine.models import load_code_model

    torch.set_num_threads(threads)
    os.environ["MODEL_PREFIX_CACHE_MB"] = str(bound_mb)
    with SandboxSettings().build() as sandbox:
        engine = Engine(sandbox, lambda: load_code_model(ModelSettings(threads=threads, quant=quant)))
        model = engine.model()
        store = model._prefixes
        load_mb = status_mb("VmHWM")
        put, added = store.put, [0]

        def counted(scope: str, entry: Any) -> None:
            added[0] += store.size(entry)
            put(scope, entry)

        store.put = counted  # type: ignore[method-assign]
        count, most_held, longest = 0, 0, 0
        start = time.perf_counter()
        with Sampler() as sampler:
            for tenant, request in requests(names, tenants):
                with scoped(tenant):
                    engine.next_action(request)
                count += 1
                most_held = max(most_held, store.held_bytes)
                longest = max(longest, *(len(tokens) for _, tokens in store._entries))
                if progress is not None:
                    with progress.open("a") as out:
                        out.write(json.dumps({"requests": count, "s": round(time.perf_counter() - start, 1),
                                              "kept_entries": len(store._entries),
                                              "kept_mib": round(store.held_bytes / MIB, 1),
                                              "added_mib": round(added[0] / MIB, 1),
                                              "rss_mb": status_mb("VmRSS"), "sampled_peak_rss_mb": sampler.peak_mb,
                                              "peak_rss_mb": status_mb("VmHWM")}) + "\n")
                if added[0] > store.max_bytes and (after := after - 1) < 0:  # more put than the bound holds
                    break
        entries = list(store._entries)
        return {
            "bound_mb": bound_mb, "dtype": model.info.dtype, "quant": getattr(model.info, "quant", quant),
            "threads": threads, "domains": names, "tenants": tenants, "requests": count,
            "filled": added[0] > store.max_bytes, "added_mib": round(added[0] / MIB, 1),
            "seconds": round(time.perf_counter() - start, 1),
            "kept_entries": len(entries), "kept_tokens": sum(len(tokens) for _, tokens in entries),
            "kept_bytes": store.held_bytes, "kept_mib": round(store.held_bytes / MIB, 1),
            "most_kept_mib": round(most_held / MIB, 1), "longest_prompt_tokens": longest,
            "load_peak_rss_mb": load_mb, "sampled_peak_rss_mb": sampler.peak_mb, "peak_rss_mb": status_mb("VmHWM"),
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--bounds-mb", nargs="+", type=int, default=[32, 768],
                        help="MODEL_PREFIX_CACHE_MB values, each in its own process (768: the old 32,768-token "
                        "bound in float32, 384 in bfloat16)")
    parser.add_argument("--domains", nargs="+", default=["Homes_1", "Restaurants_1", "Banks_1"])
    parser.add_argument("--tenants", type=int, default=3)
    parser.add_argument("--after", type=int, default=3, help="requests after the store first evicts")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--quant", default="auto", help="MODEL_QUANT (int8 where the CPU has avx2 but no VNNI)")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--progress", type=Path, help="a JSON line per request, for each bound BOUND.FILE")
    parser.add_argument("--child", nargs=7, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        bound, names, tenants, after, threads, quant, progress = args.child
        print(json.dumps(run(int(bound), names.split(","), int(tenants), int(after), int(threads), quant,
                             Path(progress) if progress else None)))
        return
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from bench.model_bench import report_rows, run_child

    threads = str(args.threads)
    rows = [run_child([str(bound), ",".join(args.domains), str(args.tenants), str(args.after), threads, args.quant,
                       str(args.progress.with_name(f"{bound}.{args.progress.name}")) if args.progress else ""],
                      __file__, threads) for bound in args.bounds_mb]
    report_rows(rows, args.json)


if __name__ == "__main__":
    main()
