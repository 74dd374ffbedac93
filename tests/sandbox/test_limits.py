"""Each configurable limit, and the isolation of the process running untrusted code."""

from __future__ import annotations

import pytest

from precond.sandbox import LimitExceeded, Limits, ProgramError, Sandbox
from precond.sandbox.policy import build_filter
from precond.sandbox.pool import ForkServer
from precond.stack.hostile_corpus import FIND

SPEC = "class A:\n    def act(self, v):\n        pass\n"
LOOP = "while True:\n    pass\n"


def trace_demo(limits: Limits, demo: str) -> object:
    with Sandbox(limits, workers=1) as sandbox:
        return sandbox.trace(SPEC, [demo])


def test_wall_clock_timeout() -> None:
    """The wall clock ends a loop before its 30 s of CPU could (how soon is a timing, not asserted here)."""
    with pytest.raises(LimitExceeded) as caught:
        trace_demo(Limits(timeout_s=1.0, cpu_s=30), LOOP)
    assert caught.value.limit == "timeout"


def test_cpu_limit() -> None:
    with pytest.raises(LimitExceeded) as caught:
        trace_demo(Limits(timeout_s=20.0, cpu_s=1), LOOP)
    assert caught.value.limit == "cpu"


def test_memory_limit() -> None:
    with pytest.raises(LimitExceeded) as caught:
        trace_demo(Limits(memory_mb=300), "x = bytearray(400 * 1024 * 1024)\n")
    assert caught.value.limit == "memory"
    trace_demo(Limits(memory_mb=300), "x = bytearray(50 * 1024 * 1024)\n")


def test_no_file_can_be_opened_even_in_the_working_directory() -> None:
    with pytest.raises(ProgramError) as caught:
        trace_demo(Limits(), FIND + "find('open')('scratch.txt', 'w')\n")
    assert caught.value.exc_type == "PermissionError"


def test_no_new_processes() -> None:
    with pytest.raises(ProgramError) as caught:
        trace_demo(Limits(), FIND + "find('fork')()\n")
    assert caught.value.exc_type == "PermissionError"


def test_output_limit() -> None:
    trace_demo(Limits(output_bytes=1000), "print('x' * 500)\n")
    with pytest.raises(LimitExceeded) as caught:
        trace_demo(Limits(output_bytes=1000), "print('x' * 2000)\n")
    assert caught.value.limit == "output"


def test_output_limit_cannot_be_swallowed() -> None:
    demo = "try:\n    print('x' * 2000)\nexcept BaseException:\n    pass\n"
    with pytest.raises(LimitExceeded) as caught:
        trace_demo(Limits(output_bytes=1000), demo)
    assert caught.value.limit == "output"


def test_result_limit() -> None:
    demo = "a = A()\n" + "".join(f"a.act({'x' * 100!r} + '{i}')\n" for i in range(100))
    trace_demo(Limits(), demo)
    with pytest.raises(LimitExceeded) as caught:
        trace_demo(Limits(result_bytes=5000), demo)
    assert caught.value.limit == "result"


def test_recursion_limit() -> None:
    demo = "def f(n):\n    return 0 if n == 0 else f(n - 1)\nf(150)\n"
    trace_demo(Limits(recursion=400), demo)
    with pytest.raises(LimitExceeded) as caught:
        trace_demo(Limits(recursion=100), demo)
    assert caught.value.limit == "recursion"


def test_network_namespace_is_an_extra_layer() -> None:
    server = ForkServer(Limits().__dict__, ["collections"], build_filter(), allow_unconfined=False)
    try:
        hello = server.ready()
        assert hello["confined"] is True
        assert hello["network_namespace"] is True or "unshare" in hello["detail"]
    finally:
        server.kill()


def test_limits_must_be_positive() -> None:
    with pytest.raises(ValueError):
        Sandbox(Limits(timeout_s=0))


def test_killed_server_is_replaced() -> None:
    with Sandbox(Limits(), workers=1) as sandbox:
        sandbox.trace(SPEC, ["a = A()"])
        for server in list(sandbox._pool._all):
            server.process.kill()
        with pytest.raises(Exception) as caught:
            sandbox.trace(SPEC, ["a = A()"])
        assert type(caught.value).__name__ == "SandboxCrashed"
        assert sandbox.trace(SPEC, ["a = A()\na.act(1)"]).actions["A.act"].occurrences


def test_concurrent_calls() -> None:
    from concurrent.futures import ThreadPoolExecutor

    with Sandbox(Limits(), workers=2) as sandbox, ThreadPoolExecutor(4) as pool:
        demos = [f"a = A()\na.act({i})" for i in range(8)]
        results = list(pool.map(lambda d: sandbox.trace(SPEC, [d]), demos))
    assert [r.actions["A.act"].arg_values for r in results] == [((i,),) for i in range(8)]


def test_unicode_identifiers_are_valid_python() -> None:
    spec = "class Dossier:\n    def __init__(self):\n        self.vérifié = False\n" \
           "    def vérifier(self):\n        self.vérifié = True\n    def clôturer(self):\n        pass\n"
    with Sandbox(Limits(), workers=1) as sandbox:
        trace = sandbox.trace(spec, ["d = Dossier()\nd.vérifier()\nd.clôturer()\n"])
        result = sandbox.evaluate(spec, ["d = Dossier()\nd.vérifier()\nd.clôturer()\n"],
                                  {"Dossier.clôturer": ["self.vérifié"]})
    assert trace.actions["Dossier.clôturer"].occurrences
    assert result.results["Dossier.clôturer"][0].status == "valid"


def test_a_limit_names_the_part_that_was_running() -> None:
    demos = ["a = A()\n", "a = A()\nwhile True:\n    pass\n"]
    with pytest.raises(LimitExceeded) as caught, Sandbox(Limits(timeout_s=5, cpu_s=1), workers=1) as sandbox:
        sandbox.trace(SPEC, demos)
    assert caught.value.limit in ("cpu", "timeout")
    assert "demonstrations[1]" in str(caught.value)
