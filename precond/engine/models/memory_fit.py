"""Whether the serving model fits the memory limit the kernel enforces on this process, checked before loading.

A container or pod limit below what the model holds resident does not fail a load with a message. The full-width
weights are a mapping of their file, so the kernel evicts and re-reads them at every decode step (the embedded
model in float32 under a 1280 MiB cgroup v1 limit: a one-line completion took 24.2 s against 1.5 s without the
limit, resident size pinned at the limit), and an allocation that eviction cannot make room for (anonymous
memory: a conversion, a batch's caches) brings the OOM killer, the orchestrator's restart, and again. The
model's weights and
how many bytes each takes are known before any of them is read (the embedded model's count is pinned with its
file; a Hugging Face directory's safetensors and a GGUF file say it in their headers), so a limit that cannot
hold them is refused with the reason, and the worker stays up to say so (`model_error`, `/ready`).

The estimate is the weight count times the bytes each takes as served, plus an overhead measured on the embedded
model (630,167,424 weights; `ru_maxrss` after a load and an 8-token completion, 2-core AMD EPYC without
avx512_vnni/avx512_bf16): float32 2,865 MiB (2,404 MiB of weights), int8 (`MODEL_QUANT=int8`) 874 MiB (601 MiB at
one byte a weight; the int8 embedding stays mapped out of the process). The count, not the weights file's size:
the file the model loads from may not exist yet (a GGUF is converted at the first load) and holds the int8
embedding that is never resident.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import torch

from precond.engine.models.store import ModelStoreError
from precond.engine.settings import EMBEDDED, ModelSettings

MIB = 1024 * 1024
EMBEDDED_WEIGHTS = 630_167_424
"""The embedded model's weight count (its sha256 is pinned, so this is too; a `model` test checks it)."""
OVERHEAD = {"none": 464 * MIB, "int8": 288 * MIB}
"""What a serving model holds beyond its weights (torch and transformers, the tokenizer, the heap a load leaves,
a first completion): measured resident size minus weights x bytes, rounded up to 16 MiB (461 MiB full-width,
273 MiB int8)."""
MARGIN = 128 * MIB
"""Room the limit must leave above the estimate: the sandbox's fork servers in the same container and a first
inference's caches (int8 serving with them peaks at 1.02 GB, 973 MiB, docs/model-speed.md; the bare model
874 MiB)."""
NO_LIMIT = 1 << 60
"""cgroup v1 writes "no limit" as the largest page-aligned 64-bit number; anything this large is none."""

CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_CGROUP = Path("/proc/self/cgroup")


class ModelTooLarge(ModelStoreError):
    """The serving model would not fit this process's memory limit: refused before loading."""


@dataclass(frozen=True)
class MemoryLimit:
    bytes: int
    source: Path


def memory_limit(root: Path = CGROUP_ROOT, membership: Path = PROC_CGROUP) -> MemoryLimit | None:
    """The lowest memory limit on this process's cgroup and the ancestors visible to it (cgroup v2 `memory.max`,
    v1 `memory.limit_in_bytes`), or None where there is none or none can be read. The own cgroup is found through
    `membership` (/proc/self/cgroup); a path not mounted here (a container without its own cgroup namespace sees
    the host's path) leaves the mount's root, which is the container's cgroup then."""
    found = [limit for path in _limit_files(root, _own_paths(membership)) if (limit := _read_limit(path))]
    return min(found, key=lambda limit: limit.bytes, default=None)


def _own_paths(membership: Path) -> dict[str, str]:
    """This process's cgroup path per hierarchy: "" for v2's unified one, "memory" for v1's memory controller."""
    try:
        lines = membership.read_text().splitlines()
    except OSError:
        return {}
    paths = {}
    for line in lines:
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        _, controllers, path = fields
        if controllers == "":
            paths[""] = path
        elif "memory" in controllers.split(","):
            paths["memory"] = path
    return paths


def _limit_files(root: Path, own: dict[str, str]) -> list[Path]:
    files = []
    for hierarchy, name in (("", "memory.max"), ("memory", "memory.limit_in_bytes")):
        base = root / hierarchy if hierarchy else root
        parts = Path(own.get(hierarchy, "/")).parts[1:]
        if ".." in parts:  # outside this cgroup namespace's root: only the mount's root is ours to read
            parts = ()
        files += [base.joinpath(*parts[:depth], name) for depth in range(len(parts), -1, -1)]
    return files


def _read_limit(path: Path) -> MemoryLimit | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    if not text.isdigit() or int(text) >= NO_LIMIT:  # v2 "max": none
        return None
    return MemoryLimit(int(text), path)


def safetensors_weights(directory: Path) -> int:
    """How many weights the safetensors files of a Hugging Face directory hold, from their headers alone."""
    total = 0
    for file in sorted(directory.glob("*.safetensors")):
        with file.open("rb") as stream:
            (length,) = struct.unpack("<Q", stream.read(8))
            header = json.loads(stream.read(length))
        total += sum(math.prod(entry["shape"]) for name, entry in header.items() if name != "__metadata__")
    return total


def gguf_weights(file: Path) -> int:
    """How many weights a GGUF file holds, from its tensor table (the file is mapped, not read)."""
    from gguf import GGUFReader

    return sum(int(tensor.n_elements) for tensor in GGUFReader(file).tensors)


@dataclass(frozen=True)
class Estimate:
    weights: int
    bytes_per_weight: int
    overhead: int
    prefixes: int = 0
    """The bound on kept prompt prefixes (`MODEL_PREFIX_CACHE_MB`): a busy worker fills it, and it stays."""

    @property
    def total(self) -> int:
        return self.weights * self.bytes_per_weight + self.overhead + self.prefixes


def estimate(weights: int, dtype: torch.dtype, quant: str, quantized_from_file: bool, prefixes: int = 0) -> Estimate:
    """Resident bytes of the served model with its kept prefixes full. int8 read from its own cache
    (`quantized_from_file`: a GGUF's, the embedded model's) holds one byte a weight; a Hugging Face directory is
    quantized after a full-width load, so its peak is the full-width model's."""
    if quant == "int8" and quantized_from_file:
        return Estimate(weights, 1, OVERHEAD["int8"], prefixes)
    return Estimate(weights, dtype.itemsize, OVERHEAD["none"], prefixes)


def check_fits(
    need: Estimate,
    limit: MemoryLimit | None,
    dtype: str,
    dtype_reason: str,
    quant: str,
    quant_reason: str,
    int8_instead: Estimate | None,
) -> None:
    """Raise ModelTooLarge, naming the choice, its reasons, the estimate, the limit and the ways out, where the
    limit cannot hold the estimate plus `MARGIN`. `int8_instead`: what `MODEL_QUANT=int8` would need here, to
    offer where it would fit."""
    if limit is None or need.total + MARGIN <= limit.bytes:
        return
    ways = [
        f"raise the limit to at least {_mib(need.total + MARGIN)} (docker compose: PRECOND_WORKER_MEMORY; "
        "Kubernetes: the worker container's resources.limits.memory)"
    ]
    if quant != "int8":
        ways.append("run on a CPU with avx512_vnni, avx_vnni or amx_int8 (MODEL_QUANT=auto then loads int8 weights)")
    if int8_instead is not None and int8_instead.total + MARGIN <= limit.bytes:
        ways.append(f"set MODEL_QUANT=int8 (~{_mib(int8_instead.total)}; slower where int8 products are emulated)")
    room = limit.bytes - (need.total - need.prefixes + MARGIN)
    if need.prefixes and room >= 0:
        ways.append(f"lower MODEL_PREFIX_CACHE_MB to at most {room // MIB} (fewer prompts kept for reuse)")
    raise ModelTooLarge(
        "the model would not fit this process's memory limit, so it is not loaded (the kernel would evict and "
        f"re-read its weights at every step, or kill the process): {need.weights:,} weights in {dtype} "
        f"({dtype_reason}), quant {quant} ({quant_reason}) "
        f"need ~{_mib(need.total)} resident ({need.bytes_per_weight} bytes a weight + {_mib(need.overhead)} + "
        f"{_mib(need.prefixes)} of kept prompt prefixes (MODEL_PREFIX_CACHE_MB)) "
        f"plus {_mib(MARGIN)} of room, over the limit of {_mib(limit.bytes)} ({limit.source}); " + "; or ".join(ways)
    )


def check_serving_memory(
    settings: ModelSettings, flags: frozenset[str] | None, dtype: tuple[torch.dtype, str], quant: tuple[str, str]
) -> None:
    """Refuse (ModelTooLarge) to load the serving model on CPU where this process's memory limit cannot hold it.
    A source whose weights cannot be counted (no safetensors, a missing file) is left to the loader to report."""
    weights, from_file = served_weights(settings.path)
    if not weights:
        return
    prefixes = settings.prefix_cache_mb * MIB
    need = estimate(weights, dtype[0], quant[0], from_file, prefixes)
    int8_instead = (estimate(weights, dtype[0], "int8", from_file, prefixes)
                    if quant[0] != "int8" and _int8_runs(flags) else None)
    check_fits(need, memory_limit(), str(dtype[0]).removeprefix("torch."), dtype[1], quant[0], quant[1], int8_instead)


def served_weights(path: str) -> tuple[int, bool]:
    """The weight count of `MODEL_PATH`'s model (0 where it cannot be counted), and whether int8 weights of it
    are read from their own file (a GGUF's cache) rather than quantized after a full-width load."""
    if path == EMBEDDED:
        return EMBEDDED_WEIGHTS, True
    source = Path(path).expanduser()
    if source.suffix == ".gguf":
        return (gguf_weights(source) if source.is_file() else 0), True
    return safetensors_weights(source), False


def _int8_runs(flags: frozenset[str] | None) -> bool:
    from precond.engine.models.quant import int8_missing

    return not int8_missing(torch.device("cpu"), flags)


def _mib(size: int) -> str:
    return f"{math.ceil(size / MIB):,} MiB"
