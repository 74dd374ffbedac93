"""Precondition sets and structured histories on a real stack (Redis, gateway, a worker with the real sandbox),
with API keys: sets are stored, versioned and owned; edits are checked against the demonstrations by the
worker; `/check-actions` takes a set reference and a history of events."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from precond.jobs.queue.keys import tenant_tag
from precond.stack.local import DEMOS, SPEC, Stack, check_body, example, infer_body, make_stack, serving
from precond.store.tenant_store import SETS
from tests.service.test_tenants import SECRET, client_for, make_key

EVENTS = [
    {"actor": "user", "act": "INFORM_INTENT", "args": ["FindRestaurants"]},
    {"actor": "system", "act": "REQUEST", "args": ["city"]},
    {"actor": "system", "act": "REQUEST", "args": ["cuisine"]},
    {"actor": "user", "act": "INFORM", "args": ["city"]},
    {"actor": "user", "act": "INFORM", "args": ["price_range"]},
]
"""examples/check-actions.json's history, as events."""


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    path = tmp_path_factory.mktemp("keys") / "keys.jsonl"
    tenants = ("acme", "globex", "small", "initech", "hooli", "umbrella", "stark", "wayne", "cyberdyne")
    return path, {tenant: make_key(path, tenant)[1] for tenant in tenants}


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path,
          keys: tuple[Path, dict[str, str]]) -> Iterator[Stack]:
    stack = make_stack(tmp_path_factory.mktemp("sets"), tiny_model_dir, PRECOND_API_KEYS_FILE=str(keys[0]),
                       PRECOND_MAX_SETS_PER_TENANT="2", PRECOND_TENANT_RATE_PER_S="1000",
                       PRECOND_TENANT_BURST="1000")
    with serving(stack, workers=1):
        yield stack


def _ok(answer: httpx.Response, status: int = 200) -> dict[str, Any]:
    assert answer.status_code == status, answer.text
    body: dict[str, Any] = answer.json()
    return body


@pytest.fixture(scope="module")
def inferred(stack: Stack, keys: tuple[Path, dict[str, str]]) -> dict[str, Any]:
    body = infer_body()
    body["options"]["library"] = False  # the demonstrations alone: the failure notice they never show has no rule
    with client_for(stack, keys[1]["acme"]) as client:
        return _ok(client.post("/infer-preconditions", json=body, params={"wait": 60}))


def _create(client: httpx.Client, inferred: dict[str, Any], **extra: Any) -> dict[str, Any]:
    body = {"spec": SPEC, "preconditions": inferred["preconditions"], "demonstrations": DEMOS, **extra}
    return _ok(client.post("/precondition-sets", json=body), 201)


def test_a_set_from_an_inference_is_stored_versioned_and_owned(
    acme: httpx.Client, globex: httpx.Client, inferred: dict[str, Any], stack: Stack
) -> None:
    made = _create(acme, inferred)
    set_id = made["id"]
    assert made["version"] == 1 and made["reference"] == f"{set_id}@1"
    assert made["preconditions"] == {a: r for a, r in inferred["preconditions"].items() if r}
    assert made["validation"]["blocked"] == []  # inferred rules allow every demonstrated call
    for path in (set_id, f"{set_id}@1", f"{set_id}/versions/1"):
        assert _ok(acme.get(f"/precondition-sets/{path}"))["preconditions"] == made["preconditions"]
    # another tenant: the same 404 as a set that does not exist
    unknown = "ps_" + "0" * 24
    theirs, missing = globex.get(f"/precondition-sets/{set_id}"), globex.get(f"/precondition-sets/{unknown}")
    assert theirs.status_code == missing.status_code == 404
    assert theirs.json()["error"]["message"].replace(set_id, unknown) == missing.json()["error"]["message"]
    assert "belong to the tenant `public`" in missing.json()["error"]["message"]  # after turning keys on
    assert globex.post(f"/precondition-sets/{set_id}/versions",
                       json={"edits": [{"op": "reject", "action": "SYSTEM.GOODBYE", "rule": "x"}]}).status_code == 404
    used = globex.post("/check-actions", json={"precondition_set": set_id, "history": EVENTS,
                                               "calls": ["system.GOODBYE()"]})
    assert used.status_code == 404, used.text
    # stored without expiry, under the owner's tag
    redis = stack.redis.client()
    tag = tenant_tag(SECRET, "acme")
    assert redis.ttl(SETS.record_key(tag, set_id)) == -1 and set_id.encode() in redis.smembers(SETS.index_key(tag))


def test_an_edit_that_blocks_a_demonstration_is_refused_unless_forced(
    acme: httpx.Client, inferred: dict[str, Any]
) -> None:
    made = _create(acme, inferred)
    set_id = made["id"]
    bad = {"op": "add", "action": "SYSTEM.INFORM", "rule": "self.user.selected"}
    refused = acme.post(f"/precondition-sets/{set_id}/versions", json={"edits": [bad]})
    assert refused.status_code == 422, refused.text
    error = refused.json()["error"]
    assert error["type"] == "blocks_demonstration" and error["field"] == "edits"
    assert "'self.user.selected' of SYSTEM.INFORM would have blocked demonstrations[" in error["message"]
    assert ", line " in error["message"] and "force" in error["message"]
    blocked = error["blocked"]  # every call it blocks, and the ways out
    assert blocked and {(b["action"], b["rule"]) for b in blocked} == {("SYSTEM.INFORM", "self.user.selected")}
    named = sorted({b["demonstration"] for b in blocked})
    assert f"the new rules block {', '.join(f'demonstrations[{d}]' for d in named[:8])}" in error["message"]
    assert all(b["call"].startswith("system.INFORM(") and b["line"] >= 1 for b in blocked)
    assert "Ways out" in error["message"] and "store the set without it" in error["message"]
    assert _ok(acme.get(f"/precondition-sets/{set_id}"))["latest"] == 1  # nothing stored
    forced = _ok(acme.post(f"/precondition-sets/{set_id}/versions", json={"edits": [bad], "force": True}), 201)
    assert forced["version"] == 2 and "self.user.selected" in forced["preconditions"]["SYSTEM.INFORM"]
    blocked = forced["validation"]["blocked"]
    assert blocked and {b["rule"] for b in blocked} == {"self.user.selected"}
    first = blocked[0]
    assert DEMOS[first["demonstration"]].splitlines()[first["line"] - 1].strip() == first["call"]
    assert first["call"].startswith("system.INFORM(")
    # reject it (kept out from now on), require another; every version stays as it was
    kept_rule = inferred["preconditions"]["SYSTEM.GOODBYE"][0]
    edited = _ok(acme.post(f"/precondition-sets/{set_id}/versions", json={"base_version": 2, "edits": [
        {"op": "reject", "action": "SYSTEM.INFORM", "rule": "self.user.selected"},
        {"op": "require", "action": "SYSTEM.GOODBYE", "rule": kept_rule},
    ]}), 201)
    assert edited["version"] == 3 and "self.user.selected" not in edited["preconditions"]["SYSTEM.INFORM"]
    assert edited["rejected"] == {"SYSTEM.INFORM": ["self.user.selected"]}
    assert edited["required"] == {"SYSTEM.GOODBYE": [kept_rule]}
    assert _ok(acme.get(f"/precondition-sets/{set_id}@2"))["preconditions"] == forced["preconditions"]
    stale = acme.post(f"/precondition-sets/{set_id}/versions",
                      json={"base_version": 2, "edits": [{"op": "remove", "action": "SYSTEM.GOODBYE",
                                                          "rule": kept_rule}]})
    assert stale.status_code == 409, stale.text
    nonsense = acme.post(f"/precondition-sets/{set_id}/versions",
                         json={"edits": [{"op": "remove", "action": "SYSTEM.GOODBYE", "rule": "no such rule"}]})
    assert nonsense.status_code == 422 and nonsense.json()["error"]["field"] == "edits[0]"
    # check-actions on a version: version 2 refuses what version 3 allows
    calls = ["system.INFORM('city')"]
    history = [*EVENTS, {"actor": "user", "act": "REQUEST", "args": ["city"]}]
    v2 = _ok(acme.post("/check-actions", json={"precondition_set": f"{set_id}@2", "history": history,
                                               "calls": calls}, params={"wait": 30}))
    latest = _ok(acme.post("/check-actions", json={"precondition_set": set_id, "history": history, "calls": calls},
                           params={"wait": 30}))
    assert v2["results"][0]["violations"] == ["self.user.selected"]
    assert latest["results"][0]["allowed"] is True


@pytest.fixture()
def hooli(stack: Stack, keys: tuple[Path, dict[str, str]]) -> Iterator[httpx.Client]:
    with client_for(stack, keys[1]["hooli"]) as client:
        yield client


def test_an_action_left_without_a_rule_is_warned_of_and_rules_compare_as_code(
    hooli: httpx.Client, inferred: dict[str, Any]
) -> None:
    assert inferred["preconditions"]["SYSTEM.NOTIFY_FAILURE"] == ["False"]  # never demonstrated: refused
    emptied = {**inferred, "preconditions": {**inferred["preconditions"], "SYSTEM.NOTIFY_FAILURE": []}}
    made = _create(hooli, emptied)
    assert made["warnings"]["SYSTEM.NOTIFY_FAILURE"].startswith("empty rule: the set has no rule for")
    assert "SYSTEM.GOODBYE" not in made["warnings"]
    only = inferred["preconditions"]["SYSTEM.GOODBYE"]
    assert len(only) == 1
    # the same rule in other quotes is the same rule: not added twice, and rejected in any spelling
    twice = hooli.post(f"/precondition-sets/{made['id']}/versions", json={"edits": [
        {"op": "add", "action": "SYSTEM.FindRestaurants", "rule": 'self.user.informed_slot["cuisine"]'}]})
    assert twice.status_code == 422 and "already has the rule" in twice.json()["error"]["message"], twice.text
    # a misspelt attribute is named as the exception it is, not counted as blocked calls
    typo = hooli.post(f"/precondition-sets/{made['id']}/versions", json={"edits": [
        {"op": "add", "action": "SYSTEM.ReserveRestaurant", "rule": "self.user.afirmed"}]})
    assert typo.status_code == 422, typo.text
    message = typo.json()["error"]["message"]
    assert message.startswith("rule 'self.user.afirmed' of SYSTEM.ReserveRestaurant raises AttributeError: 'USER' "
                              "object has no attribute 'afirmed' (demonstrations["), message
    assert "misspelt" in message and "would have blocked" not in message
    search = [{"op": "reject", "action": "SYSTEM.FindRestaurants", "rule": rule.replace("'", '"')}
              for rule in inferred["preconditions"]["SYSTEM.FindRestaurants"]]  # any spelling
    edited = _ok(hooli.post(f"/precondition-sets/{made['id']}/versions", json={"edits": [
        {"op": "reject", "action": "SYSTEM.GOODBYE", "rule": only[0]}, *search]}), 201)
    assert "SYSTEM.GOODBYE" not in edited["preconditions"]
    assert "SYSTEM.FindRestaurants" not in edited["preconditions"]
    warning = edited["warnings"]["SYSTEM.GOODBYE"]
    assert warning.startswith(f"empty rule: a reviewer rejected {only[0]!r} and no rule of SYSTEM.GOODBYE is left")
    assert warning.endswith("every call of it is allowed")
    assert "SYSTEM.FindRestaurants" in edited["warnings"]
    assert edited["warnings"]["SYSTEM.NOTIFY_FAILURE"] == made["warnings"]["SYSTEM.NOTIFY_FAILURE"]
    duplicate = _ok(hooli.post("/precondition-sets", json={"spec": SPEC, "preconditions": {
        "SYSTEM.GOODBYE": ["self.user.no_more", "self.user.no_more "], "SYSTEM.CONFIRM": [
            "self.user.informed_slot['time']", 'self.user.informed_slot["time"]']}}), 201)
    assert duplicate["preconditions"] == {"SYSTEM.GOODBYE": ["self.user.no_more"],
                                          "SYSTEM.CONFIRM": ["self.user.informed_slot['time']"]}


def test_next_action_on_a_stored_set_lists_arguments_from_its_demonstrations(
    stack: Stack, keys: tuple[Path, dict[str, str]]
) -> None:
    """The set's demonstrations name argument values (slots) the spec and history do not: with the set, the
    calls judged are those judged when the same demonstrations are sent inline."""
    inline = example("next-action")
    inline["options"] = {"return_allowed": True}
    inline["demonstrations"] = DEMOS
    with client_for(stack, keys[1]["umbrella"]) as client:  # a tenant of its own: the others are at their bound
        made = _ok(client.post("/precondition-sets", json={"spec": inline["spec"], "preconditions":
                                                           inline["preconditions"], "demonstrations": DEMOS}), 201)
        by_set = {"precondition_set": made["reference"], "history": inline["history"], "options": inline["options"]}
        direct = _ok(client.post("/next-action", json=inline, params={"wait": 60}))["actions"][0]
        stored = _ok(client.post("/next-action", json=by_set, params={"wait": 60}))["actions"][0]
    assert stored["attempts"] == direct["attempts"]
    assert stored["call"] == direct["call"] and stored["allowed"] == direct["allowed"]


def test_sets_per_tenant_are_bounded(stack: Stack, keys: tuple[Path, dict[str, str]], inferred: dict[str, Any]) -> None:
    with client_for(stack, keys[1]["small"]) as small:
        body = {"spec": SPEC, "preconditions": {"SYSTEM.GOODBYE": ["self.user.no_more"]}}
        for _ in range(2):
            _ok(small.post("/precondition-sets", json=body), 201)
        over = small.post("/precondition-sets", json=body)
    assert over.status_code == 422 and over.json()["error"]["type"] == "sets_limited", over.text


@pytest.mark.parametrize("demonstrations", [DEMOS, []], ids=["with-demonstrations", "without"])
def test_edits_past_an_actions_rule_bound_are_a_422_naming_it(stack: Stack, keys: tuple[Path, dict[str, str]],
                                                                demonstrations: list[str]) -> None:
    """40 `add` edits (each within the edit bound) on one action: the merged version would hold more rules than
    one action may have (32), so it is refused, and the set stays usable at its version 1."""
    with client_for(stack, keys[1]["wayne"]) as client:
        made = _ok(client.post("/precondition-sets", json={"spec": SPEC, "demonstrations": demonstrations,
                                                           "preconditions": {"SYSTEM.REQUEST": ["slot != ''"]}}), 201)
        edits = [{"op": "add", "action": "SYSTEM.REQUEST", "rule": f"slot != 'x{i}'"} for i in range(40)]
        over = client.post(f"/precondition-sets/{made['id']}/versions", json={"edits": edits})
        assert over.status_code == 422, over.text[:300]
        error = over.json()["error"]
        assert error["field"] == "edits" and "SYSTEM.REQUEST" in error["message"] and "32" in error["message"], error
        assert _ok(client.get(f"/precondition-sets/{made['id']}"))["latest"] == 1
        body = {"precondition_set": made["id"], "history": check_body()["history"], "calls": check_body()["calls"]}
        assert client.post("/check-actions", json=body, params={"wait": 30}).status_code == 200


def test_a_rule_that_takes_the_embedded_guard_past_its_bounds_is_a_422_naming_it_and_the_bound(
        stack: Stack, keys: tuple[Path, dict[str, str]]) -> None:
    """26 nested squarings of a constant (533 characters): refused when a set is made with it, or an edit adds
    it, before anything is stored or queued."""
    squarings = "[v0*v0 for v0 in (0xff,)]"
    for level in range(1, 26):
        squarings = f"[v{level}*v{level} for v{level} in {squarings}]"
    rule = f"len({squarings}) == 1"
    with client_for(stack, keys[1]["cyberdyne"]) as client:
        made = client.post("/precondition-sets", json={"spec": SPEC, "demonstrations": DEMOS,
                                                       "preconditions": {"SYSTEM.REQUEST": [rule]}})
        assert made.status_code == 422, made.text[:300]
        error = made.json()["error"]
        assert error["field"] == "preconditions.SYSTEM.REQUEST[0]" and error["type"] == "work_budget", error
        assert "len([v25*v25 for v25 in" in error["message"] and "262,144 bits" in error["message"], error
        kept = _ok(client.post("/precondition-sets", json={
            "spec": SPEC, "demonstrations": DEMOS,
            "preconditions": {"SYSTEM.REQUEST": ["slot != ''"]}}), 201)
        edit = client.post(f"/precondition-sets/{kept['id']}/versions",
                           json={"edits": [{"op": "add", "action": "SYSTEM.REQUEST", "rule": rule}]})
        assert edit.status_code == 422 and edit.json()["error"]["field"] == "edits", edit.text[:300]
        assert "262,144 bits" in edit.json()["error"]["message"] and _ok(
            client.get(f"/precondition-sets/{kept['id']}"))["latest"] == 1


def test_a_structured_history_judges_like_its_program(acme: httpx.Client) -> None:
    code = _ok(acme.post("/check-actions", json=check_body(), params={"wait": 30}))
    events = _ok(acme.post("/check-actions", json=check_body() | {"history": EVENTS}, params={"wait": 30}))
    assert events == code
    # what an end user typed stays a string, whatever it says
    typed = "x'); import os; os.system('id'); ('"
    hostile = [*EVENTS, {"actor": "user", "act": "REQUEST", "args": [typed]}]
    answer = _ok(acme.post("/check-actions", params={"wait": 30}, json=check_body(f"system.INFORM({typed!r})")
                           | {"history": hostile}))
    assert answer["results"][0]["allowed"] is True and answer["results"][0]["error"] is None


@pytest.mark.parametrize(("event", "words"), [
    ({"actor": "user", "act": "INFORMS", "args": ["city"]}, "unknown act 'INFORMS'"),
    ({"actor": "customer", "act": "INFORM", "args": ["city"]}, "unknown actor 'customer'"),
    ({"actor": "user", "act": "INFORM", "args": []}, "takes 1 argument"),
    ({"actor": "user", "act": "INFORM", "args": ["city", "town"]}, "takes 1 argument"),
    ({"actor": "user", "act": "INFORM", "args": [{"__class__": "x"}]}, "a dict is not allowed"),
])
def test_a_bad_event_is_a_422_naming_its_index(acme: httpx.Client, event: dict[str, Any], words: str) -> None:
    answer = acme.post("/check-actions", json=check_body() | {"history": [*EVENTS[:3], event]})
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert error["field"].startswith("history[3]") and words in error["message"], error


def test_an_event_missing_its_act_names_its_index(acme: httpx.Client) -> None:
    answer = acme.post("/check-actions", json=check_body() | {"history": [*EVENTS[:3], {"actor": "user"}]})
    assert answer.status_code == 422 and answer.json()["error"]["field"] == "history[3].act", answer.text


# two demonstrations: too thin for evidence weighting; the paper's ranking, whose rules from one demonstration the
# second refutes (the cautious default keeps more, and the rule library adds its transferred rules, which this
# diff's bookkeeping does not need)
ENUMERATE = {"generators": ["enumerate"], "tolerance": 0, "ranking": "recency", "unseen": "allow", "library": False}


@pytest.fixture()
def initech(stack: Stack, keys: tuple[Path, dict[str, str]]) -> Iterator[httpx.Client]:
    with client_for(stack, keys[1]["initech"]) as client:
        yield client


def test_reinference_keeps_required_rules_keeps_rejected_out_and_reports_a_diff(
    initech: httpx.Client, globex: httpx.Client, inferred: dict[str, Any]
) -> None:
    acme = initech  # a tenant of its own: the others are at their bound of sets
    first = _ok(acme.post("/infer-preconditions", json=infer_body(demonstrations=[DEMOS[0]], options=ENUMERATE),
                          params={"wait": 60}))
    made = _ok(acme.post("/precondition-sets", json={"spec": SPEC, "preconditions": first["preconditions"],
                                                     "demonstrations": [DEMOS[0]]}), 201)
    set_id = made["id"]

    # from DEMOS[0] alone: SYSTEM.GOODBYE needs `not self.user.affirmed`, which DEMOS[1] refutes
    assert made["preconditions"]["SYSTEM.GOODBYE"] == ["not self.user.affirmed"]
    required = "self.user.requested_slot[slot]"  # of SYSTEM.INFORM, supported by both demonstrations
    rejected = "self.query_success"  # of SYSTEM.OFFER: both support it, re-inference would bring it back
    assert required in inferred["preconditions"]["SYSTEM.INFORM"]
    assert rejected in inferred["preconditions"]["SYSTEM.OFFER"]
    marked = _ok(acme.post(f"/precondition-sets/{set_id}/versions", json={"edits": [
        {"op": "require", "action": "SYSTEM.INFORM", "rule": required},
        {"op": "reject", "action": "SYSTEM.OFFER", "rule": rejected},
    ]}), 201)
    # through the job: 202 and /jobs/{id}, like every operation
    queued = acme.post(f"/precondition-sets/{set_id}/reinfer", params={"wait": 0},
                       json={"demonstrations": [DEMOS[1], DEMOS[0]], "options": ENUMERATE, "base_version": 2})
    assert queued.status_code in (200, 202), queued.text
    if queued.status_code == 202:
        job = queued.headers["Location"]
        for _ in range(300):
            status = _ok(acme.get(job))
            if status["status"] not in ("queued", "running"):
                break
            time.sleep(0.1)
        assert status["kind"] == "reinfer" and status["status"] == "succeeded", status.get("error")
        new = status["result"]
    else:
        new = queued.json()
    assert new["version"] == 3 and new["reference"] == f"{set_id}@3"
    assert new["demonstrations"] == [DEMOS[0], DEMOS[1]]  # the union, each once
    assert required in new["preconditions"]["SYSTEM.INFORM"]
    assert rejected not in new["preconditions"].get("SYSTEM.OFFER", [])
    assert new["required"] == marked["required"] and new["rejected"] == marked["rejected"]
    diff = new["diff"]
    assert diff["base_version"] == 2 and diff["new_demonstrations"] == 1
    assert [(c["action"], c["rule"]) for c in diff["required_kept"]] == [("SYSTEM.INFORM", required)]
    assert [(c["action"], c["rule"]) for c in diff["rejected_suppressed"]] == [("SYSTEM.OFFER", rejected)]
    assert ("SYSTEM.GOODBYE", "self.user.no_more") in {(c["action"], c["rule"]) for c in diff["added"]}
    gone = {c["rule"]: c["reason"] for c in diff["removed"] if c["action"] == "SYSTEM.GOODBYE"}
    assert "demonstration" in gone["not self.user.affirmed"], gone  # where the new demonstration refutes it
    before = {(a, r) for a, rs in marked["preconditions"].items() for r in rs}
    after = {(a, r) for a, rs in new["preconditions"].items() for r in rs}
    listed = {(c["action"], c["rule"]) for part in ("kept", "required_kept", "removed") for c in diff[part]}
    assert listed == before  # every base rule is accounted for
    assert {(c["action"], c["rule"]) for c in diff["added"]} == after - before
    assert {(c["action"], c["rule"]) for c in diff["removed"]} == before - after
    assert all(c["reason"] for c in diff["removed"])
    assert new["validation"]["blocked"] == []
    assert _ok(acme.get(f"/precondition-sets/{set_id}"))["diff"] == diff  # stored with the version

    # a new demonstration that breaks the required rule: refused, naming it and its line, unless forced
    breaking = "user = USER()\nsystem = SYSTEM(user)\nsystem.INFORM('city')\n"
    body = {"demonstrations": [DEMOS[1], breaking], "options": ENUMERATE}
    refused = acme.post(f"/precondition-sets/{set_id}/reinfer", json=body, params={"wait": 60})
    assert refused.status_code == 422, refused.text
    error = refused.json()["error"]
    assert error["type"] == "blocks_demonstration" and error["field"] == "demonstrations[1]"
    assert f"required rule {required!r} of SYSTEM.INFORM" in error["message"] and "line 3" in error["message"]
    assert _ok(acme.get(f"/precondition-sets/{set_id}"))["latest"] == 3
    forced = _ok(acme.post(f"/precondition-sets/{set_id}/reinfer", json=body | {"force": True},
                           params={"wait": 60}))
    assert forced["version"] == 4 and required in forced["preconditions"]["SYSTEM.INFORM"]
    assert {(b["rule"], b["demonstration"], b["line"]) for b in forced["validation"]["blocked"]} == {
        (required, 2, 3)}

    # stale base, another tenant's or no set, bad demonstrations
    stale = acme.post(f"/precondition-sets/{set_id}/reinfer", json=body | {"base_version": 3})
    assert stale.status_code == 409 and stale.json()["error"]["type"] == "conflict", stale.text
    for client, ref in ((globex, set_id), (acme, "ps_" + "0" * 24), (acme, f"{set_id}@1")):
        assert client.post(f"/precondition-sets/{ref}/reinfer", json=body).status_code == 404
    bad = acme.post(f"/precondition-sets/{set_id}/reinfer",
                    json={"demonstrations": [DEMOS[1], "user = USER(\n"], "options": ENUMERATE})
    assert bad.status_code == 422 and bad.json()["error"]["field"] == "demonstrations[1]", bad.text
    shape = acme.post(f"/precondition-sets/{set_id}/reinfer", json={"demonstrations": [], "options": ENUMERATE})
    assert shape.status_code == 422 and shape.json()["error"]["field"] == "demonstrations", shape.text


def test_prior_sets_are_the_tenants_own_resolved_before_queueing(
    stack: Stack, keys: tuple[Path, dict[str, str]], inferred: dict[str, Any]
) -> None:
    """Another tenant's set (or one that does not exist) is a 404 here as everywhere; the tenant's own set's rules
    become priors, and the rules they decide name the set."""
    with client_for(stack, keys[1]["stark"]) as stark, client_for(stack, keys[1]["globex"]) as globex:
        made = _create(stark, inferred)
        body = infer_body(seed=32)
        body["options"]["prior_sets"] = [made["reference"]]
        answer = _ok(stark.post("/infer-preconditions", json=body, params={"wait": 60}))
        sources = {e["source"] for rules in answer["evidence"].values() for e in rules.values()
                   if e.get("decided") == "transferred"}
        assert sources == {made["reference"]}
        assert answer["preconditions"] == inferred["preconditions"]  # the demonstrations agree with the set
        # the job is the resolved rules': a new version of the set named without a version is another job
        latest = body | {"options": body["options"] | {"prior_sets": [made["id"]]}}
        before = stark.post("/infer-preconditions", json=latest, params={"wait": 60}).headers["X-Job-Id"]
        action, rules = next((a, r) for a, r in made["preconditions"].items() if r)
        _ok(stark.post(f"/precondition-sets/{made['id']}/versions",
                       json={"edits": [{"op": "remove", "action": action, "rule": rules[0]}]}), 201)
        after = stark.post("/infer-preconditions", json=latest, params={"wait": 60}).headers["X-Job-Id"]
        assert before != after
        for client, reference in ((globex, made["reference"]), (stark, "ps_" + "0" * 24)):
            refused = client.post("/infer-preconditions", json=body | {"options": body["options"] | {
                "prior_sets": [reference]}})
            assert refused.status_code == 404, refused.text
        calls = body | {"options": body["options"] | {"prior_sets": [], "prior_rules": {
            "SYSTEM.GOODBYE": ["self.user.no_more", "__import__('os').system('id')"]}}}
        bad = stark.post("/infer-preconditions", json=calls)
        assert bad.status_code == 422 and bad.json()["error"]["field"] == "options.prior_rules[SYSTEM.GOODBYE][1]"
        many = body | {"options": body["options"] | {"prior_sets": [], "prior_rules": {
            f"SYSTEM.A{i}": ["self.user.no_more"] * 32 for i in range(17)}}}
        over = stark.post("/infer-preconditions", json=many)
        assert over.status_code == 422 and "at most 512" in over.text, over.text
