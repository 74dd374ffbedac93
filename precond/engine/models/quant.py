"""Weights in 8 bits on CPU (`MODEL_QUANT`): every linear layer, the vocabulary projection and the embedding.

Decoding one token reads every weight once, so on a CPU a batch-1 step costs what the weights' bytes cost to
stream. Of the int8 kernels torch 2.13 ships for x86, measured on 2 cores of an AVX-512-VNNI EPYC at the embedded
model's layer shapes against a bfloat16 `linear` (bench/model_bench.py has the whole model):

* `torch._int_mm` (oneDNN, VNNI), with each input row quantized to int8 by its own scale: 1.6-3.1x faster at
  batch 1, 1.2-3.7x at batch 8, 1.5x on a 128-token prefill chunk. What `int8` runs (1.0-1.8x for the whole
  model's batch-1 decode: the rows' quantization and bfloat16 attention remain).
* fbgemm's dynamic int8 (`quantized::linear_dynamic`, what `quantize_dynamic` builds) is as fast, but scales the
  whole batch by one number: a row's output then depends on the rows beside it (samples would change with the
  batch), and the MLP's few huge activation channels crush the rest (logits off by 18% on a domain prompt).
* weight-only int8 and int4 (`_weight_int8pack_mm`, `_weight_int4pack_mm_for_cpu`): faster at batch 1, no faster
  at batch 8 and 1.2-2.7x slower on a prefill chunk, where the engine samples and prefills.

Per row, the logits of a 300-token domain prompt move by 7% and the top token is the same at 99% of positions.
The embedding's rows are int8 too, widened per looked-up row.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import mmap
from typing import Any

import torch
from torch import nn

from precond.engine.models.store import ModelStoreError
from precond.engine.settings import QUANT_CHOICES as QUANTS

logger = logging.getLogger(__name__)

CPU_INT8_FLAGS = ("amx_int8", "avx512_vnni", "avx_vnni")
"""int8 dot products in hardware: where `auto` quantizes (without them int8 products are emulated with 16-bit
sums, and only measuring there could show a gain)."""
CPU_INT8_REQUIRED = "avx2"
"""The least instruction set `MODEL_QUANT=int8` is accepted on (the int8 kernels' oldest path); below it the
setting is refused at load."""


class QuantUnavailable(ModelStoreError):
    """`MODEL_QUANT` names weights this machine cannot run."""


def choose_quant(name: str, device: torch.device, flags: frozenset[str] | None) -> tuple[str, str]:
    """The quantization to load with, and why (reported with the dtype in every response's `model` block).

    `auto` quantizes only where it is fast (a CPU with int8 dot products); an explicit `int8` the
    machine cannot run is an error naming the setting and what is missing, never a silent full-width model.
    """
    if name not in QUANTS:
        raise QuantUnavailable(f"MODEL_QUANT={name!r} is not one of {', '.join(QUANTS)}")
    if name == "none":
        return "none", "MODEL_QUANT=none"
    missing = int8_missing(device, flags)
    native = [flag for flag in CPU_INT8_FLAGS if flags is not None and flag in flags]
    if name == "int8":
        if missing:
            raise QuantUnavailable(f"MODEL_QUANT=int8 cannot run here: {missing}; set MODEL_QUANT=none or auto")
        if native:
            return "int8", "MODEL_QUANT=int8"
        reason = (f"MODEL_QUANT=int8 on a cpu without {'/'.join(CPU_INT8_FLAGS)}: int8 products are emulated, "
                  "slower than full-width weights here")
        logger.warning(reason)
        return "int8", reason
    if missing:
        return "none", f"no int8 weights: {missing}"
    if not native:
        return "none", f"no int8 weights: cpu without {'/'.join(CPU_INT8_FLAGS)}"
    return "int8", f"int8 weights: cpu with {native[0]}"


def int8_missing(device: torch.device, flags: frozenset[str] | None) -> str:
    """Why this machine cannot run the int8 kernels, or '' when it can."""
    if device.type != "cpu":
        return f"int8 weights are CPU kernels and the model runs on {device.type}"
    if not _int_mm_runs():
        return "this torch build cannot multiply int8 matrices on CPU (torch._int_mm)"
    if flags is None:
        return f"cpu features unknown (no /proc/cpuinfo), so {CPU_INT8_REQUIRED} cannot be checked"
    if CPU_INT8_REQUIRED not in flags:
        return f"cpu without {CPU_INT8_REQUIRED} (the int8 kernels need it)"
    return ""


QUANTIZE_ROWS = 4096
"""Rows widened to float32 at a time while quantizing: the vocabulary's 151,936 rows at once would be 0.5 GB."""


def rows_int8(weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric int8 per row, and each row's float32 scale."""
    qweight = torch.empty(weight.shape, dtype=torch.int8)
    scales = torch.empty(weight.shape[0])
    for start in range(0, weight.shape[0], QUANTIZE_ROWS):
        rows = weight[start : start + QUANTIZE_ROWS].float()
        scale = rows.abs().amax(dim=1, keepdim=True).clamp(min=1e-12) / 127.0
        qweight[start : start + QUANTIZE_ROWS] = torch.round(rows / scale).to(torch.int8)
        scales[start : start + QUANTIZE_ROWS] = scale.squeeze(1)
    return qweight, scales


def _int_mm_runs() -> bool:
    try:
        torch._int_mm(torch.ones(1, 8, dtype=torch.int8), torch.ones(8, 8, dtype=torch.int8))
    except (RuntimeError, AttributeError):
        return False
    return True


class Int8Linear(nn.Module):
    """A linear layer with per-row int8 weights; each input row (token) is quantized with its own scale and the
    product taken in int8 (`torch._int_mm`, oneDNN: VNNI where the CPU has it). Per row, so a sequence's output
    never depends on the other rows of its batch (samples stay batch-independent, `backend.uniform`).

    The weight is kept as `nn.Linear` keeps it (out x in) and handed to the kernel as a transposed view: measured
    on the 2-core EPYC (1 thread, the model's layer shapes), 2-3x faster than a transposed copy at batch 1 and as
    fast at 8-128 rows, and the layout the embedding reads, so a tied vocabulary projection and the embedding
    share one int8 matrix. An untied vocabulary projection (the embedded model's) is the exception, kept as the
    copy (`transposed`, in x out): its 151,936 rows multiply faster so at 8 rows and more (12 against 19 ms at 8
    rows, 80 against 136 ms at 128), where the engine samples and scores, and slower only at batch 1 (10 against
    6 ms)."""

    def __init__(self, qweight: torch.Tensor, scales: torch.Tensor, bias: torch.Tensor | None,
                 transposed: bool = False) -> None:
        super().__init__()
        self.transposed = transposed
        if transposed:
            self.in_features, self.out_features = qweight.shape
        else:
            self.out_features, self.in_features = qweight.shape
        self.qweight: torch.Tensor
        self.scales: torch.Tensor
        self.bias: torch.Tensor | None
        self.register_buffer("qweight", qweight)
        self.register_buffer("scales", scales)
        self.register_buffer("bias", bias)

    @classmethod
    def of(cls, linear: nn.Linear, transposed: bool = False) -> Int8Linear:
        qweight, scales = rows_int8(linear.weight.detach())
        bias = None if linear.bias is None else linear.bias.detach().float()
        return cls(qweight.t().contiguous() if transposed else qweight, scales, bias, transposed)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows = x.reshape(-1, self.in_features).float()
        row_scales = rows.abs().amax(dim=1, keepdim=True).clamp(min=1e-12) / 127.0
        weight = self.qweight if self.transposed else self.qweight.t()
        # The int32 product is dropped as soon as it is widened, and the float32 scaled in place: a vocabulary
        # projection's product is 600 KB per row, each copy of it 19 MB at 32 rows.
        out = torch._int_mm(torch.round(rows / row_scales).to(torch.int8), weight).float()
        out.mul_(row_scales).mul_(self.scales)
        if self.bias is not None:
            out.add_(self.bias)
        return out.to(x.dtype).reshape(*x.shape[:-1], self.out_features)

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, int8"


class Int8Embedding(nn.Module):
    """An embedding with per-row int8 weights: a lookup widens only the rows it reads. The rows may be a tied
    vocabulary projection's (`Int8Linear.qweight`, same layout and scales): one copy for both.

    `mapped`: the rows are a read-only mapping of the int8 file (`int8cache`). Each lookup then unmaps the
    pages it made resident (`unmap_pages`): the kernel also maps the cached pages around each one a lookup
    touches (fault-around), so a domain's prompts kept 23 MB of the embedded model's 136 MB embedding in the
    process's resident memory for good. The pages stay in the page cache, and the next lookup maps them again
    (a minor fault per row)."""

    def __init__(self, qweight: torch.Tensor, scales: torch.Tensor, dtype: torch.dtype,
                 padding_idx: int | None = None, mapped: bool = False) -> None:
        super().__init__()
        self.dtype = dtype
        self.padding_idx = padding_idx
        self.mapped = mapped
        self.qweight: torch.Tensor
        self.scales: torch.Tensor
        self.register_buffer("qweight", qweight)
        self.register_buffer("scales", scales)

    @classmethod
    def of(cls, embedding: nn.Embedding) -> Int8Embedding:
        qweight, scales = rows_int8(embedding.weight.detach())
        return cls(qweight, scales, embedding.weight.dtype, embedding.padding_idx)

    def forward(self, ids: torch.Tensor) -> torch.Tensor:
        rows = self.qweight[ids]
        if self.mapped:
            unmap_pages(self.qweight)
        return rows.to(self.dtype) * self.scales[ids].to(self.dtype)[..., None]


_MADV_DONTNEED = 4
"""madvise(2)'s advice to drop a range's pages from the process (Linux and glibc's value)."""


def unmap_pages(tensor: torch.Tensor) -> None:
    """Drop the whole pages of a tensor that maps a file read-only (MAP_PRIVATE, never written) from the process's
    resident memory; what it reads next is mapped again from the page cache, unchanged. No-op off Linux."""
    page = mmap.PAGESIZE
    start = -(-tensor.data_ptr() // page) * page
    end = (tensor.data_ptr() + tensor.nbytes) // page * page
    if end > start and _LIBC is not None:
        _LIBC.madvise(ctypes.c_void_p(start), ctypes.c_size_t(end - start), _MADV_DONTNEED)


def _libc() -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


_LIBC = _libc()


def quantize(model: Any) -> int:
    """Replace, in place, every `nn.Linear` (the vocabulary projection too) and the input embedding by int8
    versions; returns how many layers were replaced. Layer by layer, so the float32 copy a layer's quantization
    needs is one layer's, never the model's. A vocabulary projection tied to the embedding stays tied: one int8
    matrix serves both."""
    replaced = 0
    embeddings = model.get_input_embeddings()
    output = model.get_output_embeddings()
    tied = output is not None and output.weight is embeddings.weight
    shared: Int8Embedding | None = None
    for parent in list(model.modules()):
        for name, child in list(parent.named_children()):
            if child is embeddings:
                shared = Int8Embedding.of(child)
                setattr(parent, name, shared)
                replaced += 1
    for parent in list(model.modules()):
        for name, child in list(parent.named_children()):
            if isinstance(child, nn.Linear):
                if tied and child is output and shared is not None:
                    bias = None if child.bias is None else child.bias.detach().float()
                    setattr(parent, name, Int8Linear(shared.qweight, shared.scales, bias))
                else:
                    setattr(parent, name, Int8Linear.of(child, transposed=child is output))
                replaced += 1
    model.config.tie_word_embeddings = False  # the int8 modules share their tensors themselves
    _own_memory(model)
    return replaced


def _own_memory(model: Any) -> None:
    """Copy what stayed full-width (norms, biases) out of the weights file and return the freed heap: the file is
    mapped whole, so one tensor left in it keeps every replaced layer's pages resident (measured: 2.6 GB RSS
    against 1.7 GB for the full-width model)."""
    with torch.no_grad():
        for parameter in model.parameters():  # the int8 tensors are buffers of their own
            parameter.data = parameter.data.clone()
    release_heap()


def release_heap() -> None:
    """Hand freed heap back to the system (glibc keeps it otherwise): what a load parsed and dropped (the
    tokenizer's JSON, a layer's float32 copy) then no longer adds to the peak of what it reads next."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        return
