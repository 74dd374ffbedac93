"""The code-model backend: weights, loading, and fast batched completion with a shared prefix."""

from engine.models.backend import CodeModel, GenerationCancelled, Sampling, StopRule, load_code_model
from engine.models.store import ModelStoreError
from engine.settings import ModelSettings

__all__ = [
    "CodeModel",
    "GenerationCancelled",
    "ModelSettings",
    "ModelStoreError",
    "Sampling",
    "StopRule",
    "load_code_model",
]
