"""The int8 weights kept on disk, so that a worker loads them without ever holding the full-width model.

Quantizing after a full-width load peaks at the full-width model plus the int8 one (2.3-2.9 GB resident for the
embedded model). Instead, the first int8 load writes the quantized tensors once, next to the full-width cache
they come from (`<sha256>-<dtype>-int8v<format>`), reading that cache one tensor at a time; every load then
builds the model's modules on the `meta` device (no memory) and fills them from this file alone: the int8
matrices, their scales, and the few full-width tensors (norms, biases). A vocabulary projection tied to the
embedding is one int8 matrix, stored once; an untied one is stored transposed (`quant.Int8Linear`).

The file is safetensors, streamed as it is written (one tensor in memory at a time) into a temporary directory
renamed into place, with a manifest holding its sha256. A load reads it into the process's own memory while
hashing it, except an untied embedding, which is hashed and then mapped (a prompt makes only its rows resident);
a file that does not match its manifest, or was made from another source, is built again, never used. Its
location comes from the worker's settings (`MODEL_CACHE_DIR`), never from a request.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from torch import nn

from precond.engine.models.quant import Int8Embedding, Int8Linear, _own_memory, rows_int8
from precond.engine.models.store import ModelStoreError, publish

logger = logging.getLogger(__name__)

FORMAT = 2
"""Bumped whenever what is stored changes (names, layout, rounding). Part of the directory's name, so processes
of two versions sharing a cache directory keep a copy each instead of rebuilding each other's."""
WEIGHTS = "model.safetensors"
MANIFEST = "int8.json"
_DTYPES = {torch.int8: "I8", torch.float32: "F32", torch.bfloat16: "BF16", torch.float16: "F16"}
_CODES = {code: dtype for dtype, code in _DTYPES.items()}
CONFIGS = ("config.json", "generation_config.json")
_CHUNK = 1 << 22
_MAX_HEADER = 1 << 24


class _Plan:
    """What the int8 file holds, derived from the model's modules (built on `meta`) and its full-width weights:
    for each stored name, the source tensor and whether it is quantized (`qweight`/`scales`) or copied."""

    def __init__(self, model: Any, names: list[str]) -> None:
        embeddings = model.get_input_embeddings()
        output = model.get_output_embeddings()
        modules = dict(model.named_modules())
        embedding_name = next(name for name, module in modules.items() if module is embeddings)
        self.tied = output is not None and output.weight is embeddings.weight
        self.quantized = {name for name, module in modules.items()
                          if isinstance(module, nn.Linear) or module is embeddings}
        if self.tied:
            self.quantized -= {name for name, module in modules.items() if module is output}
        self.embedding = embedding_name
        self.output = next((name for name, module in modules.items() if module is output), "")
        self.transposed = "" if self.tied else self.output
        """The untied vocabulary projection, stored in x out (`quant.Int8Linear`'s `transposed`)."""
        self.copied = [name for name in names
                       if not (name.endswith(".weight") and name.removesuffix(".weight") in self.quantized)]


def _header(entries: list[tuple[str, torch.dtype, tuple[int, ...]]], metadata: dict[str, str]) -> bytes:
    """The safetensors header for tensors written in `entries`' order."""
    offset = 0
    header: dict[str, Any] = {"__metadata__": metadata}
    for name, dtype, shape in entries:
        size = torch.Size(shape).numel() * torch.empty(0, dtype=dtype).element_size()
        header[name] = {"dtype": _DTYPES[dtype], "shape": list(shape), "data_offsets": [offset, offset + size]}
        offset += size
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text


def _bytes(tensor: torch.Tensor) -> memoryview:
    array: Any = tensor.contiguous().view(torch.uint8).numpy()
    return memoryview(array).cast("B")


class _Source:
    """A full-width safetensors file read one tensor at a time with plain reads, never mapped: a mapped file's
    pages stay resident while it is open, which put the whole full-width model (1 GB) under the build's peak."""

    def __init__(self, file: Path, stream: Any) -> None:
        self.file, self.stream = file, stream
        (size,) = struct.unpack("<Q", stream.read(8))
        if size > _MAX_HEADER:
            raise ModelStoreError(f"{file}: a safetensors header of {size} bytes")
        self.header: dict[str, Any] = json.loads(stream.read(size))
        self.header.pop("__metadata__", None)
        self.base = 8 + size

    def shape(self, name: str) -> tuple[int, ...]:
        return tuple(self.header[name]["shape"])

    def tensor(self, name: str) -> torch.Tensor:
        entry = self.header[name]
        if entry["dtype"] not in _CODES:
            raise ModelStoreError(f"{self.file}: {name} is {entry['dtype']}, not a float or int8 tensor")
        tensor = torch.empty(entry["shape"], dtype=_CODES[entry["dtype"]])
        view = _bytes(tensor) if tensor.numel() else memoryview(b"")
        start, end = entry["data_offsets"]
        self.stream.seek(self.base + start)
        if end - start != len(view) or self.stream.readinto(view) != len(view):
            raise ModelStoreError(f"{self.file}: {name} is cut short")
        return tensor


def build(source: Path, target: Path, dtype: torch.dtype) -> None:
    """Write `source`'s (a full-width Hugging Face directory, one safetensors file) int8 copy to `target`.

    The source's tensors are read one at a time (`_Source`), quantized and streamed out, so the build holds one
    tensor's full-width and int8 copies at a time. Raises ModelStoreError where the source is not one file of
    plain tensors."""
    from transformers import AutoConfig, AutoModelForCausalLM

    file = source / WEIGHTS
    if not file.is_file():
        raise ModelStoreError(f"{source} has no single {WEIGHTS} to quantize")
    config = AutoConfig.from_pretrained(source)
    with torch.device("meta"):
        skeleton = AutoModelForCausalLM.from_config(config, dtype=dtype)  # type: ignore[no-untyped-call]
    with file.open("rb") as stream:
        weights = _Source(file, stream)
        names = list(weights.header)
        plan = _Plan(skeleton, names)
        missing = [m for m in plan.quantized if f"{m}.weight" not in names]
        if missing:
            raise ModelStoreError(f"{file} lacks the weights of {sorted(missing)[:3]}")
        entries: list[tuple[str, torch.dtype, tuple[int, ...]]] = []
        for module in sorted(plan.quantized):
            shape = weights.shape(f"{module}.weight")
            stored = shape[::-1] if module == plan.transposed else shape
            entries += [(f"{module}.qweight", torch.int8, stored), (f"{module}.scales", torch.float32, shape[:1])]
        for name in plan.copied:
            entries.append((name, dtype, weights.shape(name)))

        def tensors() -> Iterator[torch.Tensor]:
            for module in sorted(plan.quantized):
                qweight, scales = rows_int8(weights.tensor(f"{module}.weight"))
                yield qweight.t().contiguous() if module == plan.transposed else qweight
                yield scales
            for name in plan.copied:
                yield weights.tensor(name).to(dtype)

        target.mkdir(parents=True)
        digest = hashlib.sha256()
        metadata = {"format": str(FORMAT), "tied": str(plan.tied), "embedding": plan.embedding}
        with (target / WEIGHTS).open("wb") as out:
            head = _header(entries, metadata)
            digest.update(head)
            out.write(head)
            for (name, _, shape), tensor in zip(entries, tensors(), strict=True):
                if tuple(tensor.shape) != shape:
                    raise ModelStoreError(f"{file}: {name} changed shape while it was read")
                data = _bytes(tensor)
                digest.update(data)
                out.write(data)
            out.flush()
            os.fsync(out.fileno())
    for extra in CONFIGS:  # the modules' shapes and the end tokens; the tokenizer is the source's
        if (source / extra).is_file():
            shutil.copy2(source / extra, target / extra)
    manifest = {"format": FORMAT, "source": source.name, "sha256": digest.hexdigest()}
    (target / MANIFEST).write_text(json.dumps(manifest))


def _read(target: Path, source_name: str) -> tuple[dict[str, torch.Tensor], frozenset[str]] | None:
    """The file's tensors, read into the process's own memory while hashed, and the names of those mapped instead;
    None where it is not exactly what its manifest says (another source or format, a changed or truncated file).

    An embedding not shared with the vocabulary projection is the exception: hashed like the rest, then mapped
    from the file, so only the rows a prompt looks up become resident (136 MB of the embedded model's 633 MB
    that a decode step never reads whole), and only while it looks them up (`quant.Int8Embedding`)."""
    path = target / WEIGHTS
    try:
        manifest = json.loads((target / MANIFEST).read_text())
        if manifest.get("format") != FORMAT or manifest.get("source") != source_name:
            return None
        digest = hashlib.sha256()
        tensors: dict[str, torch.Tensor] = {}
        mapped: dict[str, tuple[int, int, list[int]]] = {}
        with path.open("rb") as stream:
            size_bytes = stream.read(8)
            (size,) = struct.unpack("<Q", size_bytes)
            if size > _MAX_HEADER:
                return None
            text = stream.read(size)
            digest.update(size_bytes + text)
            header = json.loads(text)
            metadata = header.pop("__metadata__", {})
            lazy = {f"{metadata['embedding']}.qweight"} if metadata.get("tied") == "False" else set()
            position = 0
            for name, entry in sorted(header.items(), key=lambda item: item[1]["data_offsets"][0]):
                start, end = entry["data_offsets"]
                if start != position or end < start:
                    return None
                position = end
                if name in lazy and _CODES[entry["dtype"]] is torch.int8:
                    mapped[name] = (8 + size + start, end - start, entry["shape"])
                    if not _hash_span(stream, end - start, digest):
                        return None
                    continue
                tensor = torch.empty(entry["shape"], dtype=_CODES[entry["dtype"]])
                view = _bytes(tensor) if tensor.numel() else memoryview(b"")
                if len(view) != end - start or stream.readinto(view) != len(view):
                    return None
                digest.update(view)
                tensors[name] = tensor
            if stream.read(1):
                return None
    except (OSError, ValueError, KeyError, TypeError, struct.error):
        return None
    if digest.hexdigest() != manifest.get("sha256"):
        return None
    if mapped:
        whole = torch.from_file(str(path), shared=False, size=path.stat().st_size, dtype=torch.uint8)
        for name, (offset, length, shape) in mapped.items():
            tensors[name] = whole[offset : offset + length].view(torch.int8).view(shape)
    return tensors, frozenset(mapped)


def _hash_span(stream: Any, length: int, digest: Any) -> bool:
    """Hash the next `length` bytes of `stream` through a small buffer; False where the file ends first."""
    while length:
        chunk = stream.read(min(_CHUNK, length))
        if not chunk:
            return False
        digest.update(chunk)
        length -= len(chunk)
    return True


def _assemble(directory: Path, tensors: dict[str, torch.Tensor], mapped: frozenset[str], dtype: torch.dtype) -> Any:
    """The model of `directory`'s config, its modules made on `meta` and given the int8 file's tensors (`mapped`:
    the names of those that map the file)."""
    from transformers import AutoConfig, AutoModelForCausalLM, GenerationConfig

    config = AutoConfig.from_pretrained(directory)
    with torch.device("meta"):
        model = AutoModelForCausalLM.from_config(config, dtype=dtype)  # type: ignore[no-untyped-call]
    plan = _Plan(model, [name for name, _ in model.named_parameters()])
    layers: dict[str, nn.Module] = {}
    for name in sorted(plan.quantized):
        module = model.get_submodule(name)
        qweight, scales = tensors.pop(f"{name}.qweight"), tensors.pop(f"{name}.scales")
        if isinstance(module, nn.Linear):
            layers[name] = Int8Linear(qweight, scales, None, transposed=name == plan.transposed)
        else:
            layers[name] = Int8Embedding(qweight, scales, dtype, getattr(module, "padding_idx", None),
                                         mapped=f"{name}.qweight" in mapped)
    if plan.tied:
        shared = layers[plan.embedding]
        assert isinstance(shared, Int8Embedding)
        layers[plan.output] = Int8Linear(shared.qweight, shared.scales, None)
    for name, layer in layers.items():
        bias = tensors.pop(f"{name}.bias", None)
        if isinstance(layer, Int8Linear) and bias is not None:
            layer.bias = bias.float()
        parent, _, child = name.rpartition(".")
        setattr(model.get_submodule(parent) if parent else model, child, layer)
    model.config.tie_word_embeddings = False
    unexpected = model.load_state_dict(tensors, strict=False, assign=True).unexpected_keys
    if unexpected:
        raise ModelStoreError(f"the int8 weights in {directory} hold {unexpected[:3]}, which this model lacks")
    for name, module in list(model.named_modules()):  # computed at construction, not stored: rotary frequencies
        if any(buffer.is_meta for buffer in module.buffers(recurse=False)):
            parent, _, child = name.rpartition(".")
            setattr(model.get_submodule(parent) if parent else model, child, type(module)(config=model.config))
    left = [name for name, tensor in [*model.named_parameters(), *model.named_buffers()] if tensor.is_meta]
    if left:
        raise ModelStoreError(f"the int8 weights in {directory} leave {left[:3]} unset")
    if (directory / "generation_config.json").is_file():
        model.generation_config = GenerationConfig.from_pretrained(directory)
    _own_memory(model)
    return model


def load(source: Path, cache_dir: Path, key: str, dtype: torch.dtype) -> tuple[Any, Path]:
    """The int8 model of `source` (full-width weights of cache key `key`) and where its int8 copy is; the copy
    is built first where it is missing or does not verify."""
    target = cache_dir / f"{key}-int8v{FORMAT}"
    read = _read(target, source.name) if target.is_dir() else None
    if read is None:
        if target.exists():
            logger.warning("the int8 weights in %s do not match their manifest: building them again", target)
        _build_into(source, target, dtype)
        read = _read(target, source.name)
        if read is None:
            raise ModelStoreError(f"the int8 weights just written to {target} do not read back")
    return _assemble(target, *read, dtype), target


def _build_into(source: Path, target: Path, dtype: torch.dtype) -> None:
    """Build in a scratch directory beside `target` and rename it into place (`store.publish`), replacing a
    stale copy."""
    logger.info("quantizing %s to int8 once (%s)", source, target)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=f".build-{target.name}-") as scratch:
        built = Path(scratch) / "int8"
        build(source, built, dtype)
        if target.exists():
            stale = Path(scratch) / "stale"
            with contextlib.suppress(OSError):  # another process moved it first
                os.rename(target, stale)
        publish(built, target)
