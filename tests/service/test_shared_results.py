"""Results shared between tenants (`PRECOND_SHARE_CACHE=true`) on a real stack: a shared result must be a function
of the request alone, whatever its sender ran before.

A tenant's warm sandbox child keeps what its earlier checks left in it (docs/security.md): the attacker's first
history replaces that child's verdict function, then the attacker sends the exact check the victim will send. Were
it judged on the attacker's warm child, "allowed" would be cached under the shared key and the victim's own
identical check answered from it, where the victim's rule refuses the call. The attack is on the worker's choice
of child, not on the kernel boundary (tests/sandbox/test_warm.py runs the same forgery as root and as `nobody`).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from precond.stack.keyed import KeyedStack, keyed_stack
from precond.stack.local import wait_until

FORGING: dict[str, Any] = {
    "spec": "import typing\nclass Door:\n    def open(self):\n        pass\n",
    "history": ("typing.sys.modules['precond.sandbox.child.check']._verdict = "
                "lambda *a: {'allowed': True, 'violations': [], 'error': None}\ndoor = Door()\n"),
    "calls": ["door.open()"],
}
VICTIMS_CHECK: dict[str, Any] = {
    "spec": "class Door:\n    def lock(self):\n        self.locked = True\n    def open(self):\n        pass\n",
    "preconditions": {"Door.open": ["not self.locked"]},
    "history": "door = Door()\ndoor.lock()\n",
    "calls": ["door.open()"],
}


@pytest.fixture(scope="module")
def keyed(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[KeyedStack]:
    with keyed_stack(tmp_path_factory.mktemp("shared-results"), tiny_model_dir, ("attacker", "victim"), workers=1,
                     PRECOND_SHARE_CACHE="true", SANDBOX_WORKERS="1") as keyed:
        with keyed.stack.http() as http:
            wait_until(lambda: http.get("/ready").status_code == 200, 60, "the worker's model to load")
        yield keyed


def check(keyed: KeyedStack, tenant: str, body: dict[str, Any]) -> dict[str, Any]:
    with httpx.Client(base_url=keyed.url, headers={"Authorization": f"Bearer {keyed.keys[tenant]}"},
                      timeout=60) as http:
        answer = http.post("/check-actions", json=body, params={"wait": 30})
    assert answer.status_code == 200, answer.text
    result: dict[str, Any] = answer.json()["results"][0]
    return result


def test_a_tenant_cannot_set_another_tenants_verdict_through_the_shared_cache(keyed: KeyedStack) -> None:
    check(keyed, "attacker", FORGING)  # its warm child (if it got one) now allows everything
    sent = check(keyed, "attacker", VICTIMS_CHECK)
    answered = check(keyed, "victim", VICTIMS_CHECK)
    assert answered == sent  # one shared result: the cache is on
    assert not answered["allowed"] and answered["violations"] == ["not self.locked"], answered
