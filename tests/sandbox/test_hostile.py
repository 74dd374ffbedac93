"""Hostile code as spec, demonstration, assertion and proposed call: always a structured error in time,
the caller survives, nothing leaks, and the next call works."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from sandbox_helpers import FIND, SMALL

from sandbox import LimitExceeded, ProgramError, Sandbox, SandboxCrashed, SandboxError

SPEC = "class A:\n    def __init__(self):\n        self.x = 1\n    def act(self, v):\n        pass\n"
OUTSIDE = Path("/tmp/sandbox_test_pwned")
PASSWD_MARK = "root:x:0:0"

PROGRAMS = {
    "loop": "while True:\n    pass\n",
    "fork_bomb_import": "import os\nwhile True:\n    os.fork()\n",
    "fork_bomb_walk": "while True:\n    ().__class__.__base__.__subclasses__()\n",
    "fork_bomb_getattr": FIND + "while True:\n    find('fork')()\n",
    "allocate_10gb": "x = bytearray(10 * 1024 ** 3)\n",
    "recursion": "def f():\n    return f()\nf()\n",
    "write_outside": f"open({str(OUTSIDE)!r}, 'w').write('x')\n",
    "write_outside_getattr": FIND + f"find('open')({str(OUTSIDE)!r}, 'w').write('x')\n",
    "read_passwd": "raise ValueError(open('/etc/passwd').read())\n",
    "read_passwd_getattr": FIND + "raise ValueError(find('open')('/etc/passwd').read())\n",
    "socket": "import socket\nsocket.create_connection(('127.0.0.1', 22))\n",
    "os_system": "import os\nos.system('touch /tmp/sandbox_test_pwned')\n",
    "os_system_getattr": FIND + f"find('system')('touch {OUTSIDE}')\n",
    "subclasses": "x = [c for c in ().__class__.__base__.__subclasses__()]\n",
    "dunder_import": "__import__('os').system('true')\n",
    "sys_exit": "import sys\nsys.exit(3)\n",
    "system_exit": "raise SystemExit(3)\n",
    "kill_parent": FIND + "find('kill')(find('getppid')(), 9)\n",
    "output_100mb": "print('x' * 100_000_000)\n",
    "non_utf8_output": "print('\\udcff\\udc80')\nraise ValueError('\\udcff bad \\x00')\n",
    "str_raises": "class E(Exception):\n    def __str__(self):\n        raise ValueError()\nraise E()\n",
    "str_loops": ("class E(Exception):\n    def __str__(self):\n        while True:\n            pass\n"
                  "raise E()\n"),
}

CANDIDATES = {
    "loop": "any(iter(int, 1))",
    "allocate_10gb": "len([0] * (10 * 1024 ** 3))",
    "recursion": "(lambda f: f(f))(lambda f: f(f))",
    "read_passwd": "open('/etc/passwd').read()",
    "subclasses": "().__class__.__base__.__subclasses__()",
    "dunder_import": "__import__('os').system('true')",
    "getattr": "getattr(self, 'x')",
    "output_100mb": "print('x' * 100_000_000)",
    "statement": "x = 1",
    "two_expressions": "self.x; self.x",
    "non_utf8": "'\\udcff' == v",
}

CALLS = [
    "a.act(__import__('os'))", "os.system('true')", "a.act(open('/etc/passwd').read())",
    "a.__class__.__base__()", "a.act(1); a.act(2)", "a.act(*[1])", "a.act(1)\nimport os",
    "while True: pass", "a.act('\\udcff')",
]

STRUCTURED = (ProgramError, LimitExceeded, SandboxCrashed)


def assert_still_works(sandbox: Sandbox) -> None:
    verdicts = sandbox.check(SPEC, {"A.act": ["v == 1"]}, "a = A()", ["a.act(1)", "a.act(2)"])
    assert [v.allowed for v in verdicts] == [True, False]


def run_as(sandbox: Sandbox, code: str, role: str) -> object:
    if role == "spec":
        return sandbox.trace(code + SPEC, ["a = A()"])
    if role == "demonstration":
        return sandbox.trace(SPEC, ["a = A()\n" + code])
    if role == "history":
        return sandbox.check(SPEC, {}, "a = A()\n" + code, ["a.act(1)"])
    function = "def episode():\n" + "".join(f"    {line}\n" for line in ("a = A()\n" + code).splitlines())
    return sandbox.trace(SPEC, [function])


@pytest.fixture(autouse=True)
def no_leftovers() -> None:
    OUTSIDE.unlink(missing_ok=True)


@pytest.mark.parametrize("role", ["spec", "demonstration", "history", "function_body"])
@pytest.mark.parametrize("name", sorted(PROGRAMS))
def test_hostile_program(small: Sandbox, name: str, role: str) -> None:
    start = time.monotonic()
    try:  # refused by the kernel: some attempts raise, others (os.system) just get an error code back
        text = repr(run_as(small, PROGRAMS[name], role))
    except STRUCTURED as exc:
        text = str(exc)
    assert time.monotonic() - start < SMALL.timeout_s + 5
    assert PASSWD_MARK not in text
    text.encode("utf-8")  # no lone surrogates reach the caller
    assert not OUTSIDE.exists()
    assert_still_works(small)


@pytest.mark.parametrize("name", sorted(CANDIDATES))
def test_hostile_candidate(small: Sandbox, name: str) -> None:
    start = time.monotonic()
    try:
        result = small.evaluate(SPEC, ["a = A()\na.act(1)"], {"A.act": [CANDIDATES[name]]})
    except STRUCTURED as exc:
        assert PASSWD_MARK not in str(exc)
    else:
        (candidate,) = result.results["A.act"]
        assert candidate.status in ("rejected", "invalid")
        assert PASSWD_MARK not in (candidate.reason or "")
        (candidate.reason or "").encode("utf-8")
    assert time.monotonic() - start < SMALL.timeout_s + 5
    assert_still_works(small)


def test_hostile_calls(small: Sandbox) -> None:
    verdicts = small.check(SPEC, {}, "a = A()", CALLS)
    assert [v.call for v in verdicts] == CALLS
    for verdict in verdicts[:-1]:
        assert not verdict.allowed and verdict.error, verdict
    assert verdicts[-1].allowed  # a lone surrogate is a valid literal, and harmless
    assert_still_works(small)


def test_hostile_precondition_is_program_error(small: Sandbox) -> None:
    with pytest.raises(ProgramError) as caught:
        small.check(SPEC, {"A.act": ["__import__('os')"]}, "a = A()", ["a.act(1)"])
    assert caught.value.where == "preconditions"
    assert "A.act" in caught.value.message


def test_passwd_content_never_returned(small: Sandbox) -> None:
    code = FIND + "a = A()\ntry:\n    data = find('open')('/etc/passwd').read()\nexcept Exception as e:\n" \
        "    data = str(e)\na.act(data)\n"
    try:
        result = small.trace(SPEC, [code])
    except SandboxError as exc:
        assert PASSWD_MARK not in str(exc)
    else:
        assert PASSWD_MARK not in repr(result)
        assert "Operation not permitted" in repr(result.actions["A.act"].arg_values)


def test_error_messages_are_clean(small: Sandbox) -> None:
    with pytest.raises(ProgramError) as caught:
        small.trace(SPEC, ["a = A()\nraise ValueError('\\udcff' * 10_000)"])
    error = caught.value
    assert error.where == "demonstration" and error.index == 0 and error.line == 2
    error.message.encode("utf-8")
    assert len(error.message) <= 500


def test_str_raising_gives_type_name_only(small: Sandbox) -> None:
    with pytest.raises(ProgramError) as caught:
        small.trace(SPEC, ["a = A()\n" + PROGRAMS["str_raises"]])
    assert caught.value.exc_type == "E" and caught.value.message == ""
