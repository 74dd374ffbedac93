"""The served model's weights: the device and dtype they run best in here, loading them (a GGUF converted once),
and the form serving keeps them in (quantized where `MODEL_QUANT` says, resident, its tokenizer lean). What serving
and policy training both start from (`Weights`); the code model over them is `backend.CodeModel`."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

from precond.engine.models.loading import check_built, one_at_a_time
from precond.engine.models.store import (
    EMBEDDED_NAME,
    EMBEDDED_SHA256,
    ModelStoreError,
    embedded_model_dir,
    gguf_model_dir,
)
from precond.engine.settings import EMBEDDED, ModelSettings
from precond_client.schemas import ModelInfo

logger = logging.getLogger(__name__)

_DTYPES = {
    "bfloat16": torch.bfloat16,
    "bf16": torch.bfloat16,
    "float16": torch.float16,
    "fp16": torch.float16,
    "half": torch.float16,
    "float32": torch.float32,
    "fp32": torch.float32,
    "float": torch.float32,
}

CPU_BF16_FLAGS = ("amx_bf16", "avx512_bf16")
"""CPU features with native bfloat16 dot products. Measured with bench/model_bench.py on an AVX-512-BF16 EPYC
(2 threads): bfloat16 prefills ~2x and decodes (batch 8) ~1.5-3x faster than float32 there. Without them
(emulated with ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2 on the same machine) bfloat16 is converted
element by element: prefill 28 vs 77 tok/s and batch-8 decode 2 vs 30 tok/s against float32."""

_CPUINFO = Path("/proc/cpuinfo")


def cpu_flags(cpuinfo: Path = _CPUINFO) -> frozenset[str] | None:
    """The CPU feature flags Linux reports, or None where they cannot be read (another OS)."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return None
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            return frozenset(value.split())
    return None


def cpu_dtype(flags: frozenset[str] | None, capability: str) -> tuple[torch.dtype, str]:
    """bfloat16 where the CPU has native bf16 dot products and torch uses its AVX-512 kernels, else float32.

    `capability` is `torch.backends.cpu.get_cpu_capability()`: it is lower than the hardware allows when
    torch was told so (ATEN_CPU_CAPABILITY) or built without AVX-512 kernels, and then bf16 is slow too.
    """
    if flags is None:
        return torch.float32, "cpu features unknown (no /proc/cpuinfo): float32"
    native = [flag for flag in CPU_BF16_FLAGS if flag in flags]
    if not native:
        return torch.float32, f"cpu without {'/'.join(CPU_BF16_FLAGS)}: float32"
    if not capability.upper().startswith("AVX512"):
        return torch.float32, f"cpu has {native[0]} but torch runs {capability} kernels: float32"
    return torch.bfloat16, f"cpu with {native[0]}: bfloat16"


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def choose_dtype(name: str, device: torch.device) -> tuple[torch.dtype, str]:
    """The dtype to run in, and why (reported in every response's model block)."""
    if name != "auto":
        try:
            dtype = _DTYPES[name.lower()]
        except KeyError:
            raise ValueError(f"unknown dtype {name!r}; use auto or one of {sorted(_DTYPES)}") from None
        return dtype, f"MODEL_DTYPE={name}: {_dtype_name(dtype)}"
    if device.type == "cuda":
        if torch.cuda.is_bf16_supported():
            return torch.bfloat16, "cuda with bf16: bfloat16"
        return torch.float16, "cuda without bf16: float16"
    if device.type == "cpu":
        return cpu_dtype(cpu_flags(), torch.backends.cpu.get_cpu_capability())
    return torch.float32, f"{device.type}: float32"


def _dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def _weights_dir(settings: ModelSettings, dtype: str) -> tuple[Path, str, str | None]:
    """Directory to load, display name, and the GGUF sha256 it came from (None for a plain HF directory).

    A GGUF is converted once per dtype, so the cache loads without a cast.
    """
    if settings.path == EMBEDDED:
        return embedded_model_dir(settings.cache_dir, dtype=dtype), EMBEDDED_NAME, EMBEDDED_SHA256
    path = Path(settings.path).expanduser()
    if path.suffix == ".gguf":
        directory, sha256 = gguf_model_dir(path, settings.cache_dir, dtype)
        return directory, path.stem, sha256
    if not (path / "config.json").is_file():
        raise ModelStoreError(f"MODEL_PATH {path} is neither a .gguf file nor a Hugging Face model directory")
    return path, path.name, None


@dataclass(frozen=True)
class Weights:
    """The base model as loaded (not yet placed for serving): what serving and policy training both start from."""

    model: Any
    tokenizer: Any
    info: ModelInfo
    device: torch.device


def load_weights(settings: ModelSettings) -> Weights:
    """Load (converting a GGUF once) in the dtype the device does best; sets torch's CPU thread count."""
    from transformers import AutoModelForCausalLM, AutoTokenizer

    torch.set_num_threads(settings.threads)
    device = resolve_device(settings.device)
    dtype, reason = choose_dtype(settings.dtype, device)
    with one_at_a_time():
        directory, name, sha256 = _weights_dir(settings, _dtype_name(dtype))
        tokenizer = AutoTokenizer.from_pretrained(directory)
        model = AutoModelForCausalLM.from_pretrained(
            directory, dtype=dtype, device_map=str(device) if device.type != "cpu" else None
        )
    check_built(model, directory)
    info = ModelInfo(name=name, sha256=sha256, device=str(device), dtype=_dtype_name(dtype), dtype_reason=reason)
    return Weights(model, tokenizer, info, device)


def serving_weights(settings: ModelSettings) -> Weights:
    """The weights in the form `MODEL_QUANT` picks for serving (training keeps full-width ones, `load_weights`).

    int8 weights of a GGUF (the embedded model's too) come from their own cache (`engine.models.int8cache`),
    built from the full-width one once: the process never holds the full-width model (peak resident memory
    is the int8 model's). A Hugging Face directory is loaded full-width and quantized in place.
    Raises QuantUnavailable, naming the setting and the missing CPU feature, where `int8` cannot run here, and
    ModelTooLarge, before any weight is read, where this process's memory limit cannot hold the model
    (`engine.models.memory_fit`)."""
    from transformers import AutoTokenizer

    from precond.engine.models import int8cache
    from precond.engine.models.memory_fit import check_serving_memory
    from precond.engine.models.quant import choose_quant, quantize, release_heap

    torch.set_num_threads(settings.threads)
    device = resolve_device(settings.device)
    flags = cpu_flags()
    quant, quant_reason = choose_quant(settings.quant, device, flags)
    dtype, reason = choose_dtype(settings.dtype, device)
    if device.type == "cpu":
        check_serving_memory(settings, flags, (dtype, reason), (quant, quant_reason))
    if quant != "int8":
        if settings.quant == "auto":
            logger.info("%s: weights stay full-width", quant_reason)
        weights = load_weights(settings)
    else:
        with one_at_a_time():
            directory, name, sha256 = _weights_dir(settings, _dtype_name(dtype))
        if sha256 is None:
            weights = load_weights(settings)
            logger.info("%s: %d layers quantized after loading", quant_reason, quantize(weights.model))
        else:
            tokenizer = _lean(AutoTokenizer.from_pretrained(directory))
            release_heap()  # the tokenizer's parse, before the weights are read (lower peak)
            with one_at_a_time():
                model, home = int8cache.load(directory, settings.cache_dir, directory.name, dtype)
            logger.info("%s: int8 weights read from %s", quant_reason, home)
            info = ModelInfo(name=name, sha256=sha256, device=str(device), dtype=_dtype_name(dtype),
                             dtype_reason=reason)
            weights = Weights(model, tokenizer, info, device)
    return replace(weights, info=weights.info.model_copy(update={"quant": quant, "quant_reason": quant_reason}))


_TOKENIZER_SOURCES = ("_vocab", "_merges")
"""What transformers' BPE tokenizers (Qwen2's) keep of the vocabulary they built their Rust tokenizer from, as
Python objects read only while it is built: 64 MB for the embedded model's 151,646 tokens."""


def _lean(tokenizer: Any) -> Any:
    """`tokenizer` without the Python copies of its vocabulary (`_TOKENIZER_SOURCES`): encoding and decoding run in
    the Rust tokenizer, which keeps its own. For serving only (a trained policy's tokenizer is saved whole)."""
    for name in _TOKENIZER_SOURCES:
        if isinstance(getattr(tokenizer, name, None), dict | list):
            setattr(tokenizer, name, type(getattr(tokenizer, name))())
    return tokenizer


def quantized(weights: Weights, setting: str) -> Weights:
    """`weights` (full-width, loaded by `load_weights`) in the form `MODEL_QUANT` picks, quantized in place.

    Raises QuantUnavailable, naming the setting and the missing CPU feature, where `int8` cannot run here."""
    from precond.engine.models.quant import choose_quant, quantize

    quant, reason = choose_quant(setting, weights.device, cpu_flags())
    if quant == "int8":
        layers = quantize(weights.model)
        logger.info("%s: %d layers in int8", reason, layers)
    elif setting == "auto":
        logger.info("%s: weights stay %s", reason, weights.info.dtype)
    return Weights(weights.model, weights.tokenizer,
                   weights.info.model_copy(update={"quant": quant, "quant_reason": reason}), weights.device)


def resident(model: Any) -> None:
    """Read every weight once. transformers maps the safetensors file, so the weights become resident only as a
    forward pass first reads them: the worker's memory guard would charge that to the first model job (1.9 GB
    for the embedded model in float32, over the 1 GB per-job bound). Reading them here makes the file's pages
    resident before any job, and keeps them shared: several models of one file (the evaluation's fine-tuned
    policies) share them instead of holding 2 GB each."""
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.data.sum()
