"""One real stack with API keys (Redis, gateway, one worker with the real engine and the tiny model) for the
client, the CLI's `--server` and the walkthrough."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from precond.stack.keyed import KeyedStack, keyed_stack

TENANTS = ("acme", "throttled", "cli", "walkthrough", "light", "guard")


@pytest.fixture(scope="session")
def keyed(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[KeyedStack]:
    with keyed_stack(
        tmp_path_factory.mktemp("client-stack"), tiny_model_dir, TENANTS, workers=1, PRECOND_JOB_TIMEOUT_S="120",
        # one token a second in bursts of 1000: no test runs out unless it empties its bucket on purpose
        PRECOND_TENANT_RATE_PER_S="1", PRECOND_TENANT_BURST="1000",
    ) as stack:
        yield stack
