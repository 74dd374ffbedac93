"""The serving model is refused before loading where the memory limit the kernel enforces cannot hold it: the
limit read from a cgroup tree (v2, v1, none), and the decision (estimate, margin, what the refusal says)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from precond.engine.models import ModelSettings, load_code_model, memory_fit
from precond.engine.models.memory_fit import (
    MARGIN,
    MIB,
    MemoryLimit,
    ModelTooLarge,
    check_fits,
    estimate,
    memory_limit,
    safetensors_weights,
)
from precond.engine.models.store import ModelStoreError

V1_NONE = "9223372036854771712"


def tree(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


def test_a_v2_limit_is_read_from_the_processs_own_cgroup(tmp_path: Path) -> None:
    root = tree(tmp_path / "cg", {"memory.max": "max\n", "kubepods/pod1/worker/memory.max": "1342177280\n"})
    own = tree(tmp_path, {"self": "0::/kubepods/pod1/worker\n"}) / "self"
    assert memory_limit(root, own) == MemoryLimit(1280 * MIB, root / "kubepods/pod1/worker/memory.max")


def test_the_lowest_limit_of_the_cgroup_and_its_ancestors_holds(tmp_path: Path) -> None:
    root = tree(tmp_path / "cg", {"pod/memory.max": "1000000000\n", "pod/worker/memory.max": "max\n"})
    own = tree(tmp_path, {"self": "0::/pod/worker\n"}) / "self"
    assert memory_limit(root, own) == MemoryLimit(1_000_000_000, root / "pod/memory.max")


def test_v2_max_everywhere_is_no_limit(tmp_path: Path) -> None:
    root = tree(tmp_path / "cg", {"memory.max": "max\n", "a/memory.max": "max\n"})
    assert memory_limit(root, tree(tmp_path, {"self": "0::/a\n"}) / "self") is None


def test_a_v1_limit_and_v1s_no_limit(tmp_path: Path) -> None:
    root = tree(
        tmp_path / "cg",
        {"memory/memory.limit_in_bytes": V1_NONE, "memory/docker/abc/memory.limit_in_bytes": "1342177280\n"},
    )
    own = tree(tmp_path, {"self": "4:memory:/docker/abc\n3:cpu,cpuacct:/docker/abc\n0::/\n"}) / "self"
    assert memory_limit(root, own) == MemoryLimit(1280 * MIB, root / "memory/docker/abc/memory.limit_in_bytes")
    (root / "memory/docker/abc/memory.limit_in_bytes").write_text(V1_NONE)
    assert memory_limit(root, own) is None


def test_a_path_not_mounted_here_falls_back_to_the_mounts_root(tmp_path: Path) -> None:
    """A container without its own cgroup namespace sees the host's path; its cgroup is the mount's root."""
    root = tree(tmp_path / "cg", {"memory/memory.limit_in_bytes": "536870912\n"})
    own = tree(tmp_path, {"self": "9:memory:/docker/0123abcd\n"}) / "self"
    assert memory_limit(root, own) == MemoryLimit(512 * MIB, root / "memory/memory.limit_in_bytes")


def test_no_cgroup_files_is_no_limit(tmp_path: Path) -> None:
    assert memory_limit(tmp_path / "cg", tmp_path / "missing") is None
    assert memory_limit(tree(tmp_path / "cg", {"memory.max": "garbage"}), tmp_path / "missing") is None


def test_the_estimate_is_weights_times_bytes_plus_the_measured_overhead() -> None:
    weights = memory_fit.EMBEDDED_WEIGHTS
    full = estimate(weights, torch.float32, "none", quantized_from_file=True)
    int8 = estimate(weights, torch.float32, "int8", quantized_from_file=True)
    # measured on the embedded model: 2,865 MiB float32, 874 MiB int8 (after a load and a short completion)
    assert 2_865 * MIB <= full.total <= 2_865 * MIB + 64 * MIB
    assert 874 * MIB <= int8.total <= 874 * MIB + 64 * MIB
    # int8 of a Hugging Face directory is quantized after a full-width load: its peak is the full-width model's
    assert estimate(weights, torch.bfloat16, "int8", quantized_from_file=False).bytes_per_weight == 2


def refusal(limit_mib: int, quant: str = "none") -> str:
    weights = memory_fit.EMBEDDED_WEIGHTS
    need = estimate(weights, torch.float32, quant, quantized_from_file=True)
    int8 = estimate(weights, torch.float32, "int8", quantized_from_file=True)
    with pytest.raises(ModelTooLarge) as caught:
        check_fits(
            need,
            MemoryLimit(limit_mib * MIB, Path("/sys/fs/cgroup/memory.max")),
            "float32",
            "cpu without amx_bf16/avx512_bf16: float32",
            quant,
            f"{quant} because",
            int8,
        )
    return str(caught.value)


def test_a_limit_that_cannot_hold_the_model_is_refused_naming_choice_estimate_limit_and_ways_out() -> None:
    message = refusal(1280)
    assert isinstance(ModelTooLarge(""), ModelStoreError)  # lands in the worker's model_error, a 503 to callers
    for part in (
        "float32 (cpu without amx_bf16/avx512_bf16: float32)",
        "quant none (none because)",
        "630,167,424 weights",
        "over the limit of 1,280 MiB (/sys/fs/cgroup/memory.max)",
        "PRECOND_WORKER_MEMORY",
        "resources.limits.memory",
        "avx512_vnni",
        "set MODEL_QUANT=int8",
    ):
        assert part in message, (part, message)
    assert "MODEL_QUANT=int8" not in refusal(800)  # where int8 would not fit either, it is not offered
    assert "avx512_vnni" not in refusal(800, "int8")  # int8 already: a CPU with int8 products would not help


def test_the_estimate_plus_the_margin_fits_or_is_refused() -> None:
    need = estimate(memory_fit.EMBEDDED_WEIGHTS, torch.float32, "int8", quantized_from_file=True)
    source = Path("memory.max")
    check_fits(need, MemoryLimit(need.total + MARGIN, source), "float32", "", "int8", "", None)
    check_fits(need, None, "float32", "", "int8", "", None)
    with pytest.raises(ModelTooLarge):
        check_fits(need, MemoryLimit(need.total + MARGIN - 1, source), "float32", "", "int8", "", None)


def test_the_kept_prefixes_bound_counts_in_the_estimate() -> None:
    """A full store of kept prompt prefixes is resident too: a limit that holds the model alone but not the model
    and `MODEL_PREFIX_CACHE_MB` is refused, and lowering that bound is offered."""
    bare = estimate(memory_fit.EMBEDDED_WEIGHTS, torch.float32, "int8", quantized_from_file=True)
    full = estimate(memory_fit.EMBEDDED_WEIGHTS, torch.float32, "int8", quantized_from_file=True, prefixes=256 * MIB)
    assert full.total == bare.total + 256 * MIB
    limit = MemoryLimit(bare.total + MARGIN + 64 * MIB, Path("memory.max"))
    with pytest.raises(ModelTooLarge) as caught:
        check_fits(full, limit, "float32", "", "int8", "", None)
    assert "256 MiB of kept prompt prefixes (MODEL_PREFIX_CACHE_MB)" in str(caught.value)
    assert "lower MODEL_PREFIX_CACHE_MB to at most 64" in str(caught.value)


def test_the_serving_load_is_refused_before_any_weight_is_read(
    tiny_model_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    weights = safetensors_weights(tiny_model_dir)
    assert weights == sum(
        p.numel()
        for p in load_code_model(
            ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="none")
        ).model.parameters()
    )
    monkeypatch.setattr(memory_fit, "memory_limit", lambda: MemoryLimit(64 * MIB, Path("memory.max")))

    def read(*args: object, **kwargs: object) -> None:
        raise AssertionError("weights read although the limit cannot hold them")

    monkeypatch.setattr("transformers.AutoModelForCausalLM.from_pretrained", read)
    with pytest.raises(ModelTooLarge, match=f"{weights:,} weights in float32"):
        load_code_model(ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="none"))


@pytest.mark.model
def test_the_embedded_models_pinned_weight_count_is_its_converted_files() -> None:
    """Counted on the copy this machine serves (the one `precond prepare-model` builds): a conversion keeps every
    weight whatever its dtype, so no other copy has to be built for the count."""
    from precond.engine.models.weights import _dtype_name, _weights_dir, choose_dtype, resolve_device

    settings = ModelSettings()
    dtype, _ = choose_dtype(settings.dtype, resolve_device(settings.device))
    directory, _, _ = _weights_dir(settings, _dtype_name(dtype))
    assert safetensors_weights(directory) == memory_fit.EMBEDDED_WEIGHTS


def test_a_gguf_files_weights_are_counted_from_its_tensor_table(tmp_path: Path) -> None:
    import numpy as np
    from gguf import GGUFWriter

    file = tmp_path / "model.gguf"
    writer = GGUFWriter(str(file), "qwen2")
    writer.add_tensor("token_embd.weight", np.zeros((3, 4), dtype=np.float32))
    writer.add_tensor("output_norm.weight", np.zeros(5, dtype=np.float16))
    writer.write_header_to_file()
    writer.write_kv_data_to_file()
    writer.write_tensors_to_file()
    writer.close()
    assert memory_fit.served_weights(str(file)) == (17, True)
    assert memory_fit.served_weights(str(tmp_path / "missing.gguf")) == (0, True)  # the loader says it is missing
