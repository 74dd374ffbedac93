"""Hostile requests for the API: the sandbox corpus (`stack.hostile_corpus`) in every role a client can
put code in, plus hostile HTTP bodies. Each case says which statuses are acceptable.

Roles: spec and demonstration (infer, enumerate only), history, precondition and proposed call
(check-actions), spec and history (next-action). Files the programs try to write go to canary paths in a
directory of the caller's; none may exist afterwards.

Proposed calls are the one role that answers 200: a call is the thing check-actions judges, so a hostile
call is a verdict (`allowed: false` with the reason), not a request error; the check below insists on it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from precond.stack import hostile_corpus as corpus
from precond.stack.local import DEMOS, SPEC, check_body, example, infer_body

REJECTED = (422,)
TOO_LARGE = (413,)
BAD_BODY = (400, 422)
NOT_FOUND = (404,)
ANCHOR = "system = SYSTEM(user)\n"


def _programs(canary_dir: Path) -> dict[str, str]:
    outside = str(corpus.OUTSIDE)
    canary = str(canary_dir / "pwned")
    programs = {name: code.replace(outside, canary) for name, code in corpus.PROGRAMS.items()}
    programs["write_tmp"] = f"open({str(canary_dir / 'written')!r}, 'w').write('x')\n"
    programs["os_system_touch"] = f"import os\nos.system('touch {canary_dir / 'system'}')\n"
    return programs


def _traps(canary_dir: Path) -> dict[str, tuple[str, tuple[int, ...]]]:
    """Classes that set traps for whoever touches their objects (the GC, attribute lookup, repr), each sprung
    at once. A `__del__` that raises is ignored by Python itself, so that one may also end 200."""
    touch = f"open({str(canary_dir / 'trap')!r}, 'w')"
    return {
        "del_writes": (f"class TRAP:\n  def __del__(self):\n    {touch}\nt = TRAP()\ndel t\n", (200, 422)),
        "del_loops": ("class TRAP:\n  def __del__(self):\n    while True:\n      pass\nt = TRAP()\ndel t\n",
                      REJECTED),
        "getattr_recurses": ("class TRAP:\n  def __getattr__(self, name):\n    return self.missing\n"
                             "TRAP().x\n", REJECTED),
        "getattr_loops": ("class TRAP:\n  def __getattr__(self, name):\n    while True:\n      pass\n"
                          "TRAP().x\n", REJECTED),
    }


REPR_TRAP = ("class TRAP:\n  def __repr__(self):\n    while True:\n      pass\n"
             "  def __eq__(self, other):\n    while True:\n      pass\n  def __hash__(self):\n    return 1\n")


def _spec_with(code: str) -> str:
    return SPEC + "\n" + code


def _demo_with(code: str) -> str:
    return DEMOS[0].replace(ANCHOR, ANCHOR + code, 1)


def _infer(body: dict[str, Any]) -> dict[str, Any]:
    body["options"]["generators"] = ["enumerate"]
    return body


def _nothing_verified(body: dict[str, Any]) -> str | None:
    verified = [a for a in body.get("actions", []) if a["verified"]]
    return f"verified under a hostile history: {verified}" if verified else None


def _none_allowed(body: dict[str, Any]) -> str | None:
    allowed = [r for r in body.get("results", []) if r["allowed"]]
    return f"allowed under a hostile precondition: {allowed}" if allowed else None


def _all_disallowed(body: dict[str, Any]) -> str | None:
    bad = [r for r in body.get("results", []) if r["allowed"] or not r.get("error")]
    return f"allowed or unexplained: {bad}" if bad else None


def _trap_left_out(body: dict[str, Any]) -> str | None:
    """An answered inference (200) names the hostile demonstration as left out, after the limit it ran into, and
    learned from the other one (an inference that fails whole for one demonstration is what a user must not
    get); a refusal (4xx) is checked as any other."""
    if "error" in body:
        return None
    warning = body.get("warnings", {}).get("demonstrations[0]", "")
    return None if "left out" in warning else f"demonstrations[0] not named as left out: {body.get('warnings')}"


def hostile_requests(canary_dir: Path) -> list[dict[str, Any]]:
    cases: list[dict[str, Any]] = []
    post = "POST"
    history = example("check-actions")["history"]

    programs = {name: (code, (200, 422) if name in corpus.REFUSED_QUIETLY else REJECTED)
                for name, code in _programs(canary_dir).items()}
    for name, (code, expect) in {**programs, **_traps(canary_dir)}.items():
        cases.append({"name": f"spec:{name}", "method": post, "path": "/infer-preconditions",
                      "json": _infer(infer_body(spec=_spec_with(code))), "expect": expect})
        cases.append({"name": f"history:{name}", "method": post, "path": "/check-actions",
                      "json": check_body() | {"history": history + code}, "expect": expect})
    cases.append({"name": "demonstration:repr_eq_trap_argument", "method": post, "path": "/infer-preconditions",
                  "json": _infer(infer_body(spec=SPEC + REPR_TRAP,
                                            demonstrations=[_demo_with("system.REQUEST(TRAP())\n"), DEMOS[1]])),
                  "expect": (200,), "check": _trap_left_out})  # the trap hangs: left out
    for name, (code, expect) in programs.items():
        # A demonstration that runs into a sandbox limit is left out by name and the other one teaches (200); one
        # refused before it runs is refused (422).
        limited = expect == REJECTED
        cases.append({"name": f"demonstration:{name}", "method": post, "path": "/infer-preconditions",
                      "json": _infer(infer_body(demonstrations=[_demo_with(code), DEMOS[1]])),
                      "expect": (200, *REJECTED) if limited else expect, "check": _trap_left_out if limited else None})
    for name, expression in corpus.CANDIDATES.items():
        # Preconditions judge proposed calls only: propose the action they guard.
        body = check_body("system.REQUEST('city')") | {"preconditions": {"SYSTEM.REQUEST": [expression]}}
        # A precondition that parses but cannot be evaluated is a violation: the call is refused (200).
        cases.append({"name": f"precondition:{name}", "method": post, "path": "/check-actions", "json": body,
                      "expect": (200, 422), "check": _none_allowed})
    hostile_calls = [c.replace("a.", "system.") for c in corpus.CALLS[:-1]] + [
        "system.REQUEST(__import__('os').system('touch " + str(canary_dir / "call") + "'))",
        "system.REQUEST(" + "[" * 5000 + "]" * 5000 + ")",
    ]
    cases.append({"name": "calls:corpus", "method": post, "path": "/check-actions",
                  "json": check_body(*hostile_calls), "expect": (200,), "check": _all_disallowed})
    # A well-formed call of a method the class lacks is an unknown action: 422 before anything runs.
    cases.append({"name": "calls:unknown-method", "method": post, "path": "/check-actions",
                  "json": check_body("system." + "R" * 3000 + "()"), "expect": (422,)})
    # Mode 'sample' runs the history only to judge a sampled call that parses; the tiny model's samples never
    # do, so those end 200 with nothing verified. Mode 'constrained' (the default) always runs the history in
    # the sandbox, to judge every call the agent could make: 422 or a verdict, never an escape.
    for name in ("loop", "os_system", "kill_parent", "output_100mb"):
        code = _programs(canary_dir)[name]
        for options in ({"mode": "sample", "max_attempts": 1, "max_new_tokens": 8}, {"mode": "constrained"}):
            next_action = example("next-action") | {"options": options}
            for role, changed in (("history", {"history": next_action["history"] + code}),
                                  ("spec", {"spec": _spec_with(code)})):
                cases.append({"name": f"next-action-{options['mode']}-{role}:{name}", "method": post,
                              "path": "/next-action", "json": next_action | changed, "expect": (200, 422),
                              "check": _nothing_verified})
    cases += _bodies()
    return cases


def _bodies() -> list[dict[str, Any]]:
    """Hostile requests: what the wire carries (sizes, nesting, encodings), then what the fields say."""
    return _wire_bodies() + _field_bodies()


def _wire_bodies() -> list[dict[str, Any]]:
    """Bodies hostile as bytes: too large (declared or streamed), too deep, not UTF-8, not JSON."""
    json_type = {"Content-Type": "application/json"}
    big = json.dumps(infer_body() | {"demonstrations": ["x" * (50 * 1024 * 1024)]}).encode()

    def stream(size: int) -> Any:
        async def chunks() -> Any:
            yield b'{"spec": "'
            for _ in range(size // 65536):
                yield b"x" * 65536
            yield b'"}'
        return chunks()

    deep_list = b'{"spec": "x", "history": "", "calls": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    deep_dict = (b'{"spec": "x", "history": "", "calls": ["a.b()"], "preconditions": '
                 + b'{"a": ' * 50_000 + b"1" + b"}" * 50_000 + b"}")
    return [
        {"name": "body:50MB-declared", "method": "POST", "path": "/infer-preconditions", "content": big,
         "headers": json_type, "expect": TOO_LARGE},
        {"name": "body:50MB-chunked", "method": "POST", "path": "/check-actions",
         "content": stream(50 * 1024 * 1024), "headers": json_type, "expect": TOO_LARGE},
        {"name": "body:10000-demonstrations", "method": "POST", "path": "/infer-preconditions",
         "json": infer_body(demonstrations=[DEMOS[0][:40]] * 10_000), "expect": REJECTED},
        {"name": "body:deep-json-list", "method": "POST", "path": "/check-actions", "content": deep_list,
         "headers": json_type, "expect": BAD_BODY},
        {"name": "body:deep-json-object", "method": "POST", "path": "/check-actions", "content": deep_dict,
         "headers": json_type, "expect": BAD_BODY},
        {"name": "body:non-utf8", "method": "POST", "path": "/check-actions",
         "content": b'{"spec": "\xff\xfe\xc0", "history": "", "calls": ["a.b()"]}', "headers": json_type,
         "expect": BAD_BODY},
        {"name": "body:lone-surrogate-escape", "method": "POST", "path": "/check-actions",
         "content": b'{"spec": "\\udcff", "history": "\\ud800", "calls": ["a.b(\'\\udcff\')"]}',
         "headers": json_type, "expect": REJECTED},
        {"name": "body:nul-bytes", "method": "POST", "path": "/check-actions",
         "json": check_body() | {"history": "x = 1\x00\n"}, "expect": REJECTED},
        {"name": "body:not-json", "method": "POST", "path": "/check-actions", "content": b"\x00\x01garbage",
         "headers": json_type, "expect": BAD_BODY},
        {"name": "body:wrong-content-type", "method": "POST", "path": "/check-actions",
         "content": json.dumps(check_body()).encode(), "headers": {"Content-Type": "text/plain"},
         "expect": (*BAD_BODY, 415)},
    ]


def _field_bodies() -> list[dict[str, Any]]:
    """Well-formed bodies whose fields are hostile: programs too deep, names and keys too long, odd query values."""
    deep_python = "x = " + "(" * 150 + "1" + ")" * 150 + "\n" + "y = " + "-" * 100_000 + "1\n"
    nested_lists = "z = " + "[" * 50_000 + "]" * 50_000 + "\n"
    huge_name = "A" * 150_000
    return [
        {"name": "body:deep-python-expression", "method": "POST", "path": "/infer-preconditions",
         "json": _infer(infer_body(spec=SPEC + deep_python)), "expect": REJECTED},
        {"name": "body:deep-python-lists", "method": "POST", "path": "/check-actions",
         "json": check_body() | {"history": nested_lists}, "expect": REJECTED},
        {"name": "body:huge-class-name", "method": "POST", "path": "/infer-preconditions",
         "json": _infer(infer_body(spec=f"class {huge_name}:\n  def act(self):\n    pass\n" + SPEC)),
         "expect": REJECTED},
        {"name": "body:huge-precondition-key", "method": "POST", "path": "/check-actions",
         "json": check_body() | {"preconditions": {"S" * 1_000_000: ["True"]}}, "expect": REJECTED},
        {"name": "body:huge-action-name", "method": "POST", "path": "/infer-preconditions",
         "json": _infer(infer_body(actions=["SYSTEM." + "X" * 1_000_000])), "expect": REJECTED},
        {"name": "path:huge-job-id", "method": "GET", "path": "/jobs/infer-" + "0" * 60_000,
         "expect": (*NOT_FOUND, 414, 431, 400)},
        {"name": "header:huge-request-id", "method": "POST", "path": "/check-actions",
         "json": check_body(), "headers": {"X-Request-Id": "r" * 8000}, "expect": (200, 431, 400)},
        {"name": "query:wait-negative", "method": "POST", "path": "/check-actions", "json": check_body(),
         "params": {"wait": "-1"}, "expect": REJECTED},
        {"name": "query:wait-nan", "method": "POST", "path": "/check-actions", "json": check_body(),
         "params": {"wait": "nan"}, "expect": (*REJECTED, 200)},
        {"name": "query:wait-huge", "method": "POST", "path": "/check-actions", "json": check_body(),
         "params": {"wait": "1e308"}, "expect": (200,)},
    ]
