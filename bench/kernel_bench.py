"""Which weight format multiplies fastest on this CPU: the embedded model's 24 layers' projections, timed per
kernel at the row counts the engine runs (1: a greedy next action; 8: a prompt's samples; 128: a prefill chunk).

`MODEL_QUANT=auto` quantizes only where the CPU has int8 dot products (precond/engine/models/quant.py); this is
the measurement behind that rule, and the one to run on a new kind of CPU before changing it. Each kernel is
given the weights it would hold (full-width, per-row int8, int4 in groups of 64) of random matrices of the
model's shapes; the int8 row runs the engine's own `Int8Linear`. Figures are the best of `--repeat` timings of
`--iterations` calls, in milliseconds for all 24 layers (7 projections each), with the load average beside them.

    python bench/kernel_bench.py --threads 2 --rows 1 8 128
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import torch

from precond.engine.models.quant import Int8Linear

LAYERS = 24
PROJECTIONS = {"q": (896, 896), "k": (128, 896), "v": (128, 896), "o": (896, 896),
               "gate": (4864, 896), "up": (4864, 896), "down": (896, 4864)}
"""out x in of each projection of one layer of Qwen2.5-Coder-0.5B (hidden 896, MLP 4,864, 2 key/value heads)."""
INT4_GROUP = 64
Kernel = Callable[[torch.Tensor], torch.Tensor]


def kernels(weight: torch.Tensor) -> dict[str, Kernel]:
    """Every candidate for one projection, each holding its own form of `weight` (float32, out x in)."""
    linear = torch.nn.Linear(weight.shape[1], weight.shape[0], bias=False)
    linear.weight.data = weight
    int8 = Int8Linear.of(linear)
    wide16 = weight.bfloat16()
    found: dict[str, Kernel] = {
        "float32 linear": lambda x: torch.nn.functional.linear(x, weight),
        "bfloat16 linear": lambda x: torch.nn.functional.linear(x.bfloat16(), wide16),
        "int8 x int8, per-row scales (Int8Linear)": int8,
        "int8 weight-only (_weight_int8pack_mm)": _weight_only_int8(weight),
    }
    int4 = _weight_only_int4(weight)
    if int4 is not None:
        found["int4 weight-only, groups of 64 (_weight_int4pack_mm_for_cpu)"] = int4
    return found


def _weight_only_int8(weight: torch.Tensor) -> Kernel:
    scales = weight.abs().amax(dim=1).clamp(min=1e-12) / 127.0
    qweight = torch.round(weight / scales[:, None]).to(torch.int8)
    return lambda x: torch._weight_int8pack_mm(x, qweight, scales)


def _weight_only_int4(weight: torch.Tensor) -> Kernel | None:
    out, inp = weight.shape
    groups = weight.reshape(out, inp // INT4_GROUP, INT4_GROUP)
    low, high = groups.amin(-1, keepdim=True), groups.amax(-1, keepdim=True)
    scale = (high - low).clamp(min=1e-8) / 15
    values = torch.round((groups - low) / scale).clamp(0, 15).to(torch.int32).reshape(out, inp)
    try:
        packed = torch.ops.aten._convert_weight_to_int4pack_for_cpu(values, 1)
    except (RuntimeError, AttributeError):
        return None
    zeros = low + 8 * scale
    scales_zeros = torch.stack([scale.squeeze(-1), zeros.squeeze(-1)], -1).transpose(0, 1).contiguous()
    return lambda x: torch._weight_int4pack_mm_for_cpu(x, packed, INT4_GROUP, scales_zeros)


SLOW_S = 0.2
"""A call slower than this is timed once more, not `iterations` x `repeat` times (an emulated int8 product on a CPU
without int8 dot products takes seconds per call at 128 rows)."""


def best_ms(call: Callable[[], object], iterations: int, repeat: int) -> float:
    start = time.perf_counter()
    call()
    if time.perf_counter() - start > SLOW_S:
        iterations, repeat = 1, 1
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        for _ in range(iterations):
            call()
        best = min(best, (time.perf_counter() - start) / iterations)
    return best * 1000


def layer_ms(rows: int, iterations: int, repeat: int) -> dict[str, float]:
    """Milliseconds per kernel for one layer's projections at `rows` input rows, times LAYERS."""
    torch.manual_seed(0)
    totals: dict[str, float] = {}
    for out, inp in PROJECTIONS.values():
        x = torch.randn(rows, inp)
        with torch.no_grad():
            for name, kernel in kernels(torch.randn(out, inp) * 0.02).items():
                totals[name] = totals.get(name, 0.0) + best_ms(partial(kernel, x), iterations, repeat)
    return {name: LAYERS * ms for name, ms in totals.items()}


def cpu_name() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").is_file() else []:
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rows", type=int, nargs="+", default=[1, 8, 128])
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"{cpu_name()}, torch {torch.__version__} ({torch.backends.cpu.get_cpu_capability()}), "
          f"{args.threads} threads, load average before {os.getloadavg()[0]:.1f}")
    results = {rows: layer_ms(rows, args.iterations, args.repeat) for rows in args.rows}
    names = list(next(iter(results.values())))
    print("\n| kernel | " + " | ".join(f"{rows} rows, ms" for rows in args.rows) + " |")
    print("|---|" + "---|" * len(args.rows))
    for name in names:
        print(f"| {name} | " + " | ".join(f"{results[rows][name]:.1f}" for rows in args.rows) + " |")
    print(f"\nload average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
