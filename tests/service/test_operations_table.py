"""Every kind a route submits through `answer` has one row of `OPERATIONS`: what the gateway does with its body
first (complete it, the model its answer depends on, its static check), looked up by kind, never by the type
of the body. A check is the exception: its route screens it, and judges it where it can, in one trip to the
check pool (`offload.screened_check`)."""

from __future__ import annotations

from typing import get_args

import pytest

from precond.gateway import offload
from precond.gateway.routes.operations import OPERATIONS
from precond.jobs.queue.kinds import KINDS, covers
from precond.programs import checks
from precond_client.schemas import JobKind


def test_every_submitted_kind_has_a_row() -> None:
    assert set(OPERATIONS) == set(get_args(JobKind)) - {"validate", "check"}  # their routes submit them
    assert set(OPERATIONS) == {kind for kind, row in KINDS.items() if row.answered}


def test_a_layer_table_that_misses_a_kind_is_refused_naming_it() -> None:
    with pytest.raises(RuntimeError, match=r"missing \['train-policy'\]"):
        covers("table", [kind for kind in KINDS if kind != "train-policy"], KINDS)
    with pytest.raises(RuntimeError, match=r"not job kinds here \['translate'\]"):
        covers("table", [*KINDS, "translate"], KINDS)


def test_the_screen_of_a_check_reads_the_rendered_calls() -> None:
    spec = "class S:\n  def a(self): pass\n"
    outcome = offload.screened_check(spec, {"S.a": ["True"]}, {}, "s = S()\n", ["s.a()"], "tenant-tag", 1_000)
    assert outcome == offload.Queued("s = S()\n", ["s.a()"])  # not a converter's spec: the sandbox judges it
    refused = offload.screened_check(spec, {"S.a": ["True"]}, {}, "s = S()\n", ["s.b()"], "tenant-tag", 1_000)
    assert isinstance(refused, checks.Problem) and refused.field == "calls[0]"
    assert OPERATIONS["reinfer"].check_args is None
