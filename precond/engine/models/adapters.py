"""A trained policy as files: a LoRA adapter (peft's format, so any peft user can load it) and what trained it.

An adapter directory holds `adapter_model.safetensors` (the weights: safetensors, never a pickle),
`adapter_config.json` (peft's, written for other tools and never read here) and `policy.json` (the
`TrainPolicyResult`: the base model it was trained on, its rank, its losses). Loading trusts none of it: the
sizes are bounded before reading, the base must be the one this process serves, the weights must be exactly
the tensors the rank and the base model's attention projections call for. The evaluation merges an adapter into
full-width weights; a worker serving it beside the base model, and `precond next-action --adapter`, keep it
unmerged (`lora_weights`, `backend.with_adapter`): a few MB per adapter over shared weights.
"""

from __future__ import annotations

import ast
import hashlib
import os
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any, NamedTuple

from pydantic import ValidationError

from precond_client.schemas import ModelInfo
from precond_client.schemas.errors import InvalidInput
from precond_client.schemas.training import MAX_ADAPTER_BYTES, TrainPolicyResult

TARGET_MODULES = ("q_proj", "k_proj", "v_proj", "o_proj")
WEIGHTS = "adapter_model.safetensors"
RESULT = "policy.json"
MAX_RESULT_BYTES = 1_000_000
LORA_ALPHA_PER_RANK = 2


class Lora(NamedTuple):
    """One module's low-rank change, `b @ a`, already scaled (peft's `lora_alpha / rank`)."""

    a: Any
    b: Any


class AdapterError(InvalidInput):
    """An adapter that cannot be used here (or saved), and why."""

    def __init__(self, message: str) -> None:
        super().__init__(message, field="adapter")


def lora_config(rank: int) -> Any:
    from peft import LoraConfig

    return LoraConfig(r=rank, lora_alpha=LORA_ALPHA_PER_RANK * rank, target_modules=list(TARGET_MODULES),
                      lora_dropout=0.0, bias="none", task_type="CAUSAL_LM")


def with_lora(model: Any, rank: int) -> Any:
    """`model` with LoRA layers of `rank` (peft's `get_peft_model`). peft reads transformers'
    `is_gradient_checkpointing`, which warns of its own deprecation each time (a FutureWarning in every training
    and adapter load, about code that is not ours): that one warning is silenced here, no other."""
    from peft import get_peft_model

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*is_gradient_checkpointing.*", category=FutureWarning)
        return get_peft_model(model, lora_config(rank))


def save_adapter(peft_model: Any, directory: Path, result: TrainPolicyResult) -> TrainPolicyResult:
    """Written whole or not at all: a temporary directory beside the target, renamed into place once complete
    and within MAX_ADAPTER_BYTES (a cancelled or oversized training leaves nothing behind)."""
    directory.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(dir=directory.parent, prefix=f".{directory.name}-"))
    try:
        peft_model.save_pretrained(scratch, safe_serialization=True)
        size = (scratch / WEIGHTS).stat().st_size
        if size > MAX_ADAPTER_BYTES:
            raise AdapterError(f"the adapter is {size} bytes, over the limit of {MAX_ADAPTER_BYTES}: lower "
                               "options.rank")
        result = result.model_copy(update={"adapter_bytes": size})
        (scratch / RESULT).write_text(result.model_dump_json(indent=1))
        if directory.exists():
            shutil.rmtree(directory)
        os.replace(scratch, directory)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return result


def read_result(directory: Path) -> TrainPolicyResult:
    path = directory / RESULT
    if not path.is_file() or path.stat().st_size > MAX_RESULT_BYTES:
        raise AdapterError(f"{directory}: no {RESULT} (or over {MAX_RESULT_BYTES} bytes): not a trained policy")
    try:
        return TrainPolicyResult.model_validate_json(path.read_bytes())
    except ValidationError as exc:
        raise AdapterError(f"{path}: {exc.errors()[0]['msg']} at {exc.errors()[0]['loc']}") from None


def merge_adapter(model: Any, directory: Path, base: ModelInfo) -> tuple[str, TrainPolicyResult]:
    """Merge the adapter at `directory` into `model` (in place); its name for the `model` block of responses,
    and what trained it."""
    name, result, data = _read_adapter(directory, base)
    _load_into(model, data, result.options.rank)
    return name, result


def lora_weights(model: Any, directory: Path, base: ModelInfo) -> tuple[str, TrainPolicyResult, dict[str, Lora]]:
    """The adapter at `directory` as low-rank pairs per module of `model` it changes, left unmerged: checked
    against the module names and sizes of `model` (full-width or int8) exactly as a merge checks them."""
    name, result, data = _read_adapter(directory, base)
    rank = result.options.rank
    tensors = _tensors(data)
    expected: dict[str, tuple[int, ...]] = {}
    for module, layer in model.named_modules():
        if module.rsplit(".", 1)[-1] in TARGET_MODULES:
            expected[f"base_model.model.{module}.lora_A.weight"] = (rank, layer.in_features)
            expected[f"base_model.model.{module}.lora_B.weight"] = (layer.out_features, rank)
    _check_fit(tensors, expected, rank)
    scale = LORA_ALPHA_PER_RANK  # lora_alpha / rank, as peft scales it
    pairs = {key.removeprefix("base_model.model.").removesuffix(".lora_A.weight"):
             Lora(tensors[key], tensors[key.replace("lora_A", "lora_B")] * scale)
             for key in expected if key.endswith("lora_A.weight")}
    return name, result, pairs


def _read_adapter(directory: Path, base: ModelInfo) -> tuple[str, TrainPolicyResult, bytes]:
    """Name, what trained it (its known calls filtered) and the weights' bytes, bounded and checked against
    the served base model before anything is parsed."""
    result = read_result(directory)
    if (result.base_model, result.base_sha256) != (base.name, base.sha256):
        raise AdapterError(f"{directory}: trained on {result.base_model} ({result.base_sha256}), but this process "
                           f"serves {base.name} ({base.sha256})")
    weights = directory / WEIGHTS
    if not weights.is_file() or weights.stat().st_size > MAX_ADAPTER_BYTES:
        raise AdapterError(f"{directory}: no {WEIGHTS} of at most {MAX_ADAPTER_BYTES} bytes")
    data = weights.read_bytes()
    calls = [c for c in result.calls if _one_call(c)]
    name = f"{directory.name}@{hashlib.sha256(data).hexdigest()[:12]}"
    return name, result.model_copy(update={"calls": calls}), data


def _one_call(text: str) -> bool:
    """A known call must be what training wrote, one call expression; anything else is left out, never run."""
    try:
        body = ast.parse(text).body
    except (SyntaxError, ValueError, RecursionError):
        return False
    return len(body) == 1 and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Call)


def _tensors(data: bytes) -> dict[str, Any]:
    from safetensors import SafetensorError
    from safetensors.torch import load as load_tensors

    try:
        return load_tensors(data)
    except SafetensorError as exc:
        raise AdapterError(f"{WEIGHTS} is not a safetensors file: {exc}") from None


def _check_fit(tensors: dict[str, Any], expected: dict[str, Any], rank: int) -> None:
    if set(tensors) != set(expected):
        extra = sorted(set(tensors) - set(expected))[:3]
        missing = sorted(set(expected) - set(tensors))[:3]
        raise AdapterError(f"{WEIGHTS} does not fit this model at rank {rank}: unexpected {extra}, missing {missing}")
    wrong = [k for k, t in tensors.items() if tuple(t.shape) != tuple(expected[k])]
    if wrong:
        raise AdapterError(f"{WEIGHTS}: {wrong[0]} has shape {tuple(tensors[wrong[0]].shape)}, "
                           f"expected {tuple(expected[wrong[0]])}")


def _load_into(model: Any, data: bytes, rank: int) -> None:
    from peft import set_peft_model_state_dict

    tensors = _tensors(data)
    peft_model = with_lora(model, rank)
    _check_fit(tensors, {k.replace(".default", ""): v.shape for k, v in peft_model.state_dict().items()
                         if "lora_" in k}, rank)
    set_peft_model_state_dict(peft_model, tensors)
    peft_model.merge_and_unload()
