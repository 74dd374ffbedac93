"""Every kind a route submits through `answer` has one row of `OPERATIONS`: what the gateway does with its body
first (complete it, the model its answer depends on, its static check), looked up by kind, never by the type
of the body."""

from __future__ import annotations

from typing import get_args

from precond.gateway.routes.operations import OPERATIONS
from precond_client.schemas.api import CheckRequest, JobKind


def test_every_submitted_kind_has_a_row() -> None:
    assert set(OPERATIONS) == set(get_args(JobKind)) - {"validate"}  # a set's validation: its route submits it


def test_the_static_check_of_a_check_reads_the_rendered_calls() -> None:
    body = CheckRequest(spec="class S:\n  def a(self): pass\n", preconditions={"S.a": ["True"]},
                        history="s = S()\n", calls=["s.a()"])
    static_check = OPERATIONS["check"].static_check
    assert static_check is not None
    check, args = static_check(body, 1_000, "tenant-tag")
    assert check.__name__ == "check_check" and args[-2:] == (["s.a()"], "tenant-tag")
    assert OPERATIONS["check"].model(body) is None and OPERATIONS["reinfer"].static_check is None
