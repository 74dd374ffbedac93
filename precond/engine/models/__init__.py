"""The code-model backend: weights, loading, and fast batched completion with a shared prefix."""

from precond.engine.models.backend import CodeModel, GenerationCancelled, Sampling, StopRule, load_code_model
from precond.engine.models.store import ModelStoreError
from precond.engine.settings import ModelSettings

__all__ = [
    "CodeModel",
    "GenerationCancelled",
    "ModelSettings",
    "ModelStoreError",
    "Sampling",
    "StopRule",
    "load_code_model",
]
