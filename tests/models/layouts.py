"""Comparing two numerical layouts of the same rows (a shared prefix or a copied one, alone or in a batch).

Two layouts run other matrix shapes, and a CPU's kernels may add in another order for each: logits of the same
row can differ in their last bits, enough to move a sampled token of the tiny random model, whose distribution
over its vocabulary is nearly flat. So a layout test does not compare samples alone: the first run records
every row's logits at every step, keyed by the row's own random number (a function of the seed, the row's suffix
and sample index and the step, the same in any layout); the second run is given the first run's tokens, so both
read the same texts, and its logits are compared within `TOLERANCE`. The model runs in float32 with float32
weights (`quant="none"`): with int8 weights, which `quant` auto serves on a CPU with avx512_vnni, every layer
rounds its input rows to int8, so a last-bit difference between layouts can become a whole int8 step (0.14 in a
logit of the tiny model on an AVX-512 AMD EPYC).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

import pytest
import torch

from precond.engine.models import backend

TOLERANCE = 1e-3
"""Most a logit may differ between two layouts of the same row (float32; the tiny model's logits are O(1))."""

Steps = dict[float, tuple[torch.Tensor, int]]
T = TypeVar("T")
U = TypeVar("U")


@contextmanager
def recorded(monkeypatch: pytest.MonkeyPatch) -> Iterator[Steps]:
    """Within the block, every sampled row-step's logits and token, by the row's random number."""
    steps: Steps = {}
    sample = backend.sample_next

    def recording(logits: torch.Tensor, sampling: backend.Sampling, uniforms: torch.Tensor) -> torch.Tensor:
        before = logits.float().clone()  # as the step computed them (sampling scales its float32 logits in place)
        tokens = sample(logits, sampling, uniforms)
        for row, key in enumerate(uniforms.tolist()):
            steps[key] = (before[row], int(tokens[row]))
        return tokens

    with monkeypatch.context() as patched:
        patched.setattr(backend, "sample_next", recording)
        yield steps


@contextmanager
def replayed(monkeypatch: pytest.MonkeyPatch, steps: Steps) -> Iterator[list[float]]:
    """Within the block, every row-step takes the recorded token; yields each step's largest logit difference."""
    differences: list[float] = []

    def replaying(logits: torch.Tensor, _sampling: backend.Sampling, uniforms: torch.Tensor) -> torch.Tensor:
        tokens = []
        for row, key in enumerate(uniforms.tolist()):
            assert key in steps, "a row-step that the first layout never sampled"
            expected, token = steps[key]
            differences.append(float((logits[row].float() - expected).abs().max()))
            tokens.append(token)
        return torch.tensor(tokens, device=logits.device)

    with monkeypatch.context() as patched:
        patched.setattr(backend, "sample_next", replaying)
        yield differences


def in_two_layouts(monkeypatch: pytest.MonkeyPatch, first: Callable[[], T], second: Callable[[], U]) -> tuple[T, U]:
    """Both runs' results, `second` given the tokens `first` sampled; fails unless the two runs' logits agree within
    `TOLERANCE` at every step of every row that `second` runs."""
    with recorded(monkeypatch) as steps:
        expected = first()
    with replayed(monkeypatch, steps) as differences:
        got = second()
    assert differences and max(differences) <= TOLERANCE, f"logits differ by up to {max(differences):.2e}"
    return expected, got
