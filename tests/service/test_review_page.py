"""The review page (/ui/) in a real browser (Debian's Chromium, driven by Playwright) on a real stack with API
keys, and the list endpoint it reads: a rule rejected by a click is rejected in version 2 through the API,
the try-it panel refuses what the rules refuse, what the API refuses is shown where it belongs, and the
page never turns a tenant's text into markup."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from precond.jobs.queue.keys import tenant_tag
from precond.stack import browser
from precond.stack.local import DEMOS, EXAMPLES, SPEC, Stack, make_stack, serving
from precond.store.tenant_store import SETS
from precond_client.schemas import rule_status
from tests.engine.test_counterexamples import CANCEL
from tests.engine.test_counterexamples import DEMOS as AIRLINE
from tests.engine.test_counterexamples import run as airline_run
from tests.service import test_precondition_sets as sets_tests
from tests.service.test_tenants import SECRET, client_for

if browser.missing() is None:
    from playwright.sync_api import Browser, Page, expect
else:
    Browser = Page = Any  # type: ignore[misc,assignment]

keys, inferred, _ok = sets_tests.keys, sets_tests.inferred, sets_tests._ok  # the same tenants and inference, on a
# stack of this module's (its `acme` and `globex` clients: tests/service/conftest.py)
needs_browser = pytest.mark.skipif(browser.missing() is not None, reason=f"no browser: {browser.missing()}")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path,
          keys: tuple[Path, dict[str, str]]) -> Iterator[Stack]:
    stack = make_stack(tmp_path_factory.mktemp("ui"), tiny_model_dir, PRECOND_API_KEYS_FILE=str(keys[0]),
                       PRECOND_TENANT_RATE_PER_S="1000", PRECOND_TENANT_BURST="1000",
                       PRECOND_MAX_BODY_BYTES=str(4 * 1024 * 1024), PRECOND_MAX_SET_COUNTEREXAMPLES="1")
    with serving(stack, workers=1):
        yield stack


def _create(client: httpx.Client, inferred: dict[str, Any], **extra: Any) -> dict[str, Any]:
    body = {"spec": SPEC, "preconditions": inferred["preconditions"], "demonstrations": DEMOS,
            "evidence": inferred["evidence"], "candidates": inferred["candidates"], "warnings": inferred["warnings"],
            **extra}
    return _ok(client.post("/precondition-sets", json=body), 201)


# -- the API the page reads --------------------------------------------------------------------------------------

def test_check_actions_with_a_set_names_how_each_refusing_rule_was_decided(
    acme: httpx.Client, inferred: dict[str, Any]
) -> None:
    made = _create(acme, inferred)
    refused = _ok(acme.post("/check-actions", params={"wait": 30}, json={
        "precondition_set": made["reference"], "history": [{"actor": "user", "act": "INFORM", "args": ["city"]}],
        "calls": ["system.FindRestaurants()", "system.NOTIFY_FAILURE()"]}))
    for verdict in refused["results"]:
        assert not verdict["allowed"] and verdict["violations"], verdict
        action = "SYSTEM." + verdict["call"].split(".")[1].split("(")[0]
        assert verdict["decided"] == {rule: made["decided"][action][rule] for rule in verdict["violations"]}
    assert refused["results"][1]["decided"] == {"False": "unseen"}  # never demonstrated: refused, and says why
    assert [v["rule_status"] for v in refused["results"]] == [
        rule_status(made["preconditions"]["SYSTEM.FindRestaurants"], made["decided"]["SYSTEM.FindRestaurants"]),
        "missing"]  # allowed or refused because nothing is known says so


def test_next_action_with_a_set_says_what_each_judged_calls_rule_rests_on(
    acme: httpx.Client, inferred: dict[str, Any]
) -> None:
    """The set's labels reach a next action as they reach a check: a refused call of the never-demonstrated
    failure notice says 'missing', the others what their inference decided."""
    made = _create(acme, inferred)
    [action] = _ok(acme.post("/next-action", params={"wait": 60}, json={
        "precondition_set": made["reference"], "history": [{"actor": "user", "act": "INFORM", "args": ["city"]}],
        "options": {"mode": "constrained"}}))["actions"]
    statuses = {r["action"]: r["rule_status"] for r in action["rejected"]}
    assert statuses["SYSTEM.NOTIFY_FAILURE"] == "missing"
    assert statuses["SYSTEM.FindRestaurants"] == rule_status(made["preconditions"]["SYSTEM.FindRestaurants"],
                                                            made["decided"]["SYSTEM.FindRestaurants"]) != "given"
    assert action["rule_status"] == rule_status(made["preconditions"].get(action["action"], []),
                                                made["decided"].get(action["action"], {}))


def test_a_set_keeps_its_inference_report_and_says_how_each_rule_was_decided(
    acme: httpx.Client, inferred: dict[str, Any]
) -> None:
    made = _create(acme, inferred)
    assert made["evidence"] == inferred["evidence"] and made["candidates"] == inferred["candidates"]
    assert made["warnings"] == inferred["warnings"]
    decided = made["decided"]
    assert decided.keys() == made["preconditions"].keys()
    for action, rules in made["preconditions"].items():
        for rule in rules:
            evidence = inferred["evidence"][action][rule]
            assert decided[action][rule] == evidence["decided"], (action, rule)  # the engine's word, kept
            # two demonstrations: no rule rests on calls in 3 of them, so none is established
            assert decided[action][rule] != "established", (action, rule)
    # an edit carries the report on; a rule added by hand has no inference's evidence, but the check against the
    # demonstrations that let it in is evidence too: validated at every demonstrated call of its action
    edited = _ok(acme.post(f"/precondition-sets/{made['id']}/versions", json={"edits": [
        {"op": "add", "action": "SYSTEM.GOODBYE", "rule": "self.user is not None"}]}), 201)
    assert edited["evidence"] == made["evidence"]
    assert edited["decided"]["SYSTEM.GOODBYE"]["self.user is not None"] == "validated"
    assert edited["validation"]["occurrences"]["SYSTEM.GOODBYE: self.user is not None"] == len(DEMOS)


def test_a_set_without_rules_is_refused_saying_how_to_learn_them(acme: httpx.Client) -> None:
    """Sent with demonstrations but no rules, a set would allow every call of every action: refused, not stored."""
    for body in ({"spec": SPEC, "demonstrations": DEMOS}, {"spec": SPEC, "demonstrations": DEMOS,
                                                           "preconditions": {"SYSTEM.INFORM": []}}):
        answer = acme.post("/precondition-sets", json=body)
        assert answer.status_code == 422, answer.text
        error = answer.json()["error"]
        assert error["field"] == "preconditions" and "/infer-preconditions" in error["message"], error


def test_the_list_is_the_tenants_own_newest_first_and_paged(
    stack: Stack, keys: tuple[Path, dict[str, str]], inferred: dict[str, Any], globex: httpx.Client
) -> None:
    with client_for(stack, keys[1]["initech"]) as lister:
        assert _ok(lister.get("/precondition-sets")) == {"sets": [], "total": 0, "offset": 0, "limit": 20,
                                                         "next_offset": None}
        by_hand = _ok(lister.post("/precondition-sets", json={
            "spec": SPEC, "preconditions": {"SYSTEM.GOODBYE": ["self.user.no_more"]}}), 201)
        made = [by_hand, _create(lister, inferred), _create(lister, inferred)]
        second = _ok(lister.post(f"/precondition-sets/{made[1]['id']}/versions", json={"edits": [
            {"op": "reject", "action": "SYSTEM.GOODBYE", "rule": inferred["preconditions"]["SYSTEM.GOODBYE"][0]}]}),
            201)
        page = _ok(lister.get("/precondition-sets", params={"limit": 2}))
        assert page["total"] == 3 and page["next_offset"] == 2 and len(page["sets"]) == 2
        rest = _ok(lister.get("/precondition-sets", params={"limit": 2, "offset": 2}))
        assert rest["next_offset"] is None
        listed = page["sets"] + rest["sets"]
        assert [s["created"] for s in listed] == sorted((s["created"] for s in listed), reverse=True)
        assert {s["id"] for s in listed} == {m["id"] for m in made}
        summary = {s["id"]: s for s in listed}
        hand = summary[by_hand["id"]]
        assert (hand["rules"], hand["no_evidence"], hand["assumed"], hand["latest"]) == (1, 1, 0, 1)
        edited = summary[second["id"]]
        labels = [label for rules in second["decided"].values() for label in rules.values()]
        assert edited["latest"] == 2 and edited["reference"] == f"{second['id']}@2" and edited["rejected"] == 1
        assert edited["rules"] == len(labels) and edited["assumed"] == labels.count("assumed") > 0
        assert set(edited["actions"]) == set(inferred["candidates"])
        assert _ok(globex.get("/precondition-sets"))["total"] == 0  # another tenant's sets are not there
        assert lister.get("/precondition-sets", params={"limit": 0}).status_code == 422
    assert stack.http().get("/precondition-sets").status_code == 401


def test_a_set_stored_before_summaries_is_listed_from_its_versions(
    stack: Stack, acme: httpx.Client, inferred: dict[str, Any]
) -> None:
    made = _create(acme, inferred)
    _ok(acme.post(f"/precondition-sets/{made['id']}/versions", json={"edits": [
        {"op": "remove", "action": "SYSTEM.GOODBYE", "rule": made["preconditions"]["SYSTEM.GOODBYE"][0]}]}), 201)
    stack.redis.client().hdel(SETS.record_key(tenant_tag(SECRET, "acme"), made["id"]), "created", "summary")
    listed = {s["id"]: s for s in _ok(acme.get("/precondition-sets", params={"limit": 100}))["sets"]}
    old = listed[made["id"]]
    assert (old["created"], old["latest"]) == (made["created"], 2)
    assert old["rules"] == sum(len(r) for r in made["preconditions"].values()) - 1


def test_the_page_is_served_without_a_key_outside_the_openapi_document(stack: Stack) -> None:
    with stack.http() as http:
        for path in ("/ui/", "/ui/sets/ps_" + "a" * 24, "/ui/sets/ps_" + "a" * 24 + "@3"):
            page = http.get(path)
            assert page.status_code == 200 and page.headers["content-type"].startswith("text/html"), path
            assert "script-src 'self'" in page.headers["content-security-policy"]
            assert page.headers["x-content-type-options"] == "nosniff"
        assert http.get("/ui", follow_redirects=False).headers["location"] == "/ui/"
        script = http.get("/ui/static/app.js")
        assert script.status_code == 200 and script.headers["content-type"].startswith("text/javascript")
        for path in ("/ui/sets/not-a-set", "/ui/static/..%2f..%2fapp.py", "/ui/static/keys.jsonl", "/ui/nothing"):
            missing = http.get(path)
            assert missing.status_code == 404 and "<main" in missing.text, path
        paths = http.get("/openapi.json").json()["paths"]
        assert "/precondition-sets" in paths and not [p for p in paths if p.startswith("/ui")]


@pytest.mark.stack
def test_the_page_is_under_the_rate_limit(tmp_path: Path, tiny_model_dir: Path) -> None:
    stack = make_stack(tmp_path, tiny_model_dir, PRECOND_TENANT_RATE_PER_S="0.01", PRECOND_TENANT_BURST="3")
    with serving(stack), stack.http() as http:
        answers = [http.get("/ui/").status_code for _ in range(4)]
        limited = http.get("/ui/static/app.js")
    assert answers == [200, 200, 200, 429]
    assert limited.status_code == 429 and int(limited.headers["retry-after"]) >= 1
    assert limited.json()["error"]["type"] == "rate_limited"


# -- in the browser -------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def chromium() -> Iterator[Browser]:
    if browser.missing() is not None:
        pytest.skip(f"no browser: {browser.missing()}")
    with browser.chromium() as launched:
        yield launched


@pytest.fixture()
def page(chromium: Browser) -> Iterator[Page]:
    context = chromium.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    page.set_default_timeout(30_000)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    yield page
    context.close()
    assert not errors, errors  # no script error on any page


def _open(page: Page, stack: Stack, path: str, key: str) -> None:
    """Open a page and give the key when it asks (once per tab)."""
    page.goto(stack.base_url + path)
    dialog = page.locator("#key-dialog")
    dialog.wait_for()
    dialog.locator("input").fill(key)
    dialog.locator("button").click()


@pytest.fixture()
def opened(page: Page, stack: Stack, keys: tuple[Path, dict[str, str]], acme: httpx.Client,
           inferred: dict[str, Any]) -> dict[str, Any]:
    """A new set of acme's from the inference, open in the page."""
    made = _create(acme, inferred)
    _open(page, stack, f"/ui/sets/{made['id']}", keys[1]["acme"])
    return made


def _rule(page: Page, action: str, rule: str) -> Any:
    return page.locator(f"section.action[data-action='{action}'] li.rule").filter(
        has=page.locator("code", has_text=rule))


@needs_browser
def test_rejecting_a_rule_by_a_click_makes_version_2(
    page: Page, acme: httpx.Client, opened: dict[str, Any], keys: tuple[Path, dict[str, str]]
) -> None:
    made = opened
    rule = "self.query_success"
    assert rule in made["preconditions"]["SYSTEM.OFFER"]
    item = _rule(page, "SYSTEM.OFFER", rule)
    expect(item.locator(".badge").first).to_have_text(made["decided"]["SYSTEM.OFFER"][rule])
    expect(item.locator(".evidence")).to_contain_text("held at")
    expect(item.locator(".reason")).to_contain_text("kept")
    item.locator("button[data-op=reject]").click()
    page.wait_for_url(f"**/ui/sets/{made['id']}@2")
    expect(page.locator("#set-head")).to_contain_text("version 2 of 2")
    # its only rule: the action now has none, and says why
    expect(page.locator("#no-rule li[data-action='SYSTEM.OFFER']")).to_contain_text("a reviewer rejected")
    expect(page.locator("#no-rule li[data-action='SYSTEM.OFFER'] .rejected")).to_contain_text(rule)
    latest = _ok(acme.get(f"/precondition-sets/{made['id']}"))
    assert latest["version"] == 2 and latest["rejected"] == {"SYSTEM.OFFER": [rule]}
    assert rule not in latest["preconditions"].get("SYSTEM.OFFER", [])
    assert keys[1]["acme"] not in page.url
    # the version history shows what made version 2, and the difference from version 1
    page.locator("#history-details summary").click()
    expect(page.locator("#versions")).to_contain_text(f"reject SYSTEM.OFFER: {rule}")
    expect(page.locator("#diff .removed")).to_contain_text(rule)


@needs_browser
def test_actions_without_a_rule_are_a_warning_in_the_header_never_an_all_clear(
    page: Page, stack: Stack, acme: httpx.Client, keys: tuple[Path, dict[str, str]]
) -> None:
    made = _ok(acme.post("/precondition-sets", json={
        "spec": SPEC, "preconditions": {"SYSTEM.GOODBYE": ["self.user.no_more"]}}), 201)
    without = len(made["warnings"])
    assert without > 1 and "SYSTEM.GOODBYE" not in made["warnings"]
    _open(page, stack, f"/ui/sets/{made['id']}", keys[1]["acme"])
    expect(page.locator("#no-rule-count")).to_have_text(f"{without} actions without a rule: every call allowed")
    expect(page.locator("#review-count")).not_to_have_class("badge d-established")


def _event(row: Any, actor: str, act: str, args: str) -> None:
    for name, value in (("actor", actor), ("act", act), ("args", args)):
        row.locator(f"[name={name}]").fill(value)


@needs_browser
def test_the_try_it_panel_refuses_a_call_the_rules_refuse(
    page: Page, acme: httpx.Client, opened: dict[str, Any]
) -> None:
    made = opened
    assert "self.user.requested_slot[slot]" in made["preconditions"]["SYSTEM.INFORM"]
    _event(page.locator("#try-events .event").first, "user", "INFORM_INTENT", "FindRestaurants")
    page.locator("#try-calls").fill("system.INFORM('phone_number')\nsystem.REQUEST('city')")
    page.locator("#try-check").click()
    refused = page.locator("#try-results .verdict[data-call=\"system.INFORM('phone_number')\"]")
    expect(refused).to_have_class("verdict refused")
    expect(refused).to_contain_text("self.user.requested_slot[slot]")
    status = rule_status(made["preconditions"]["SYSTEM.INFORM"], made["decided"]["SYSTEM.INFORM"])
    expect(refused).to_have_attribute("data-status", status)  # what the verdict rests on, on the page too
    expect(refused.locator(f".badge.d-{status}")).to_have_text(status)
    # the user asks for it: now allowed
    page.locator("#try-add-event").click()
    second = page.locator("#try-events .event").nth(1)
    _event(second, "user", "REQUEST", "phone_number")
    page.locator("#try-check").click()
    expect(page.locator("#try-results .verdict").first).to_have_class("verdict allowed")
    # an event the API refuses: its message, naming the event
    second.locator("[name=act]").fill("SHOUT")
    page.locator("#try-check").click()
    expect(page.locator("#try-error")).to_contain_text("SHOUT")


@needs_browser
def test_a_judged_call_that_should_have_been_refused_is_learned_from_by_a_click(
    page: Page, stack: Stack, acme: httpx.Client, keys: tuple[Path, dict[str, str]]
) -> None:
    """"this should have been refused" on an allowed call: the set's next version refuses it, its rule names it on
    the page, and the set's bound of counterexamples (1 on this stack) is a 422 naming the setting."""
    demos = [t.program for i, t in enumerate(AIRLINE.trajectories) if i != 2]  # no basic economy demonstrated
    inferred = _ok(acme.post("/infer-preconditions", params={"wait": 120}, json={
        "spec": AIRLINE.spec, "demonstrations": demos, "actions": [CANCEL],
        "options": {"generators": ["enumerate"]}}))
    made = _ok(acme.post("/precondition-sets", json={
        "spec": AIRLINE.spec, "preconditions": inferred["preconditions"], "demonstrations": demos,
        "evidence": inferred["evidence"], "candidates": inferred["candidates"]}), 201)
    _open(page, stack, f"/ui/sets/{made['id']}", keys[1]["acme"])
    page.locator("#try-json").fill(json.dumps(airline_run("F6", "economy", "no")[:3]))
    call = "agent.cancel_reservation('F6')"
    page.locator("#try-calls").fill(call)
    page.locator("#try-check").click()
    allowed = page.locator(f"#try-results .verdict[data-call=\"{call}\"]")
    expect(allowed).to_have_class("verdict allowed")
    allowed.locator("button.counterexample").click()
    page.wait_for_url(f"**/ui/sets/{made['id']}@2")
    latest = _ok(acme.get(f"/precondition-sets/{made['id']}"))
    name = f"review 1: {call}"
    assert latest["version"] == 2 and latest["counterexamples"][0]["calls"][0] == {
        "line": 6, "verdict": "refuse", "name": name}
    refusing = [rule for rule, e in latest["evidence"][CANCEL].items() if name in e["refuses"]]
    assert refusing and set(refusing) <= set(latest["preconditions"][CANCEL])
    expect(_rule(page, CANCEL, refusing[0]).locator(".refuses")).to_contain_text(name)
    page.locator("#try-json").fill(json.dumps(airline_run("F6", "economy", "no")[:3]))
    page.locator("#try-calls").fill(call)
    page.locator("#try-check").click()
    refused = page.locator(f"#try-results .verdict[data-call=\"{call}\"]")
    expect(refused).to_have_class("verdict refused")
    expect(refused.locator("button.counterexample")).to_have_text("this should have been allowed")
    over = acme.post(f"/precondition-sets/{made['id']}/counterexamples", json={
        "history": airline_run("H8", "business", "no")[:3], "call": "agent.cancel_reservation('H8')",
        "verdict": "allow"})
    assert over.status_code == 422 and over.json()["error"]["type"] == "sets_limited", over.text
    assert "PRECOND_MAX_SET_COUNTEREXAMPLES" in over.json()["error"]["message"]


@needs_browser
def test_the_try_it_panel_takes_a_pasted_json_history(page: Page, opened: dict[str, Any]) -> None:
    """A history of 13 events is one paste, not 13 rows: events, or an agent's OpenAI messages, as JSON."""
    made = opened
    assert "self.user.requested_slot[slot]" in made["preconditions"]["SYSTEM.INFORM"]
    pasted = [{"actor": "user", "act": "INFORM_INTENT", "args": ["FindRestaurants"]},
              {"actor": "user", "act": "REQUEST", "args": ["phone_number"]}]
    page.locator("#try-json").fill(json.dumps(pasted, indent=2))
    page.locator("#try-calls").fill("system.INFORM('phone_number')\nsystem.INFORM('address')")
    page.locator("#try-check").click()
    expect(page.locator("#try-results .verdict[data-call=\"system.INFORM('phone_number')\"]")).to_have_class(
        "verdict allowed")
    expect(page.locator("#try-results .verdict[data-call=\"system.INFORM('address')\"]")).to_have_class(
        "verdict refused")
    # a history that already broke a rule says where and which
    page.locator("#try-json").fill(json.dumps([pasted[0], {"actor": "system", "act": "INFORM", "args": ["city"]}]))
    page.locator("#try-check").click()
    expect(page.locator("#try-history-violation")).to_contain_text("line 4")
    expect(page.locator("#try-history-violation")).to_contain_text("self.user.requested_slot[slot]")
    # what is not a JSON list, and an event the API refuses, are said, naming the place
    page.locator("#try-json").fill("{not json")
    page.locator("#try-check").click()
    expect(page.locator("#try-error")).to_contain_text("pasted history: not JSON")
    page.locator("#try-json").fill(json.dumps([{"actor": "user", "act": "SHOUT"}]))
    page.locator("#try-check").click()
    expect(page.locator("#try-error")).to_contain_text("SHOUT")


@needs_browser
def test_an_added_rule_that_blocks_a_demonstration_shows_the_apis_refusal_at_its_action(
    page: Page, acme: httpx.Client, opened: dict[str, Any]
) -> None:
    made = opened
    form = page.locator("section.action[data-action='SYSTEM.INFORM'] form.add-rule")
    form.locator("input").fill("self.user.selected")
    form.locator("button[type=submit]").click()
    error = form.locator(".error")
    expect(error).to_contain_text("'self.user.selected' of SYSTEM.INFORM would have blocked demonstration")
    expect(error).to_contain_text("Ways out")  # and which demonstrations it blocks, each call listed
    expect(error.locator("ul.blocked li").first).to_contain_text("blocked by SYSTEM.INFORM: self.user.selected")
    assert _ok(acme.get(f"/precondition-sets/{made['id']}"))["latest"] == 1
    error.locator("button.force").click()  # keep it anyway: version 2, its blocked calls shown in their code
    page.wait_for_url(f"**/ui/sets/{made['id']}@2")
    added = _rule(page, "SYSTEM.INFORM", "self.user.selected")
    expect(added.locator(".badge").first).to_have_text("no evidence")
    marked = added.locator(".line.marked").first
    expect(marked).to_contain_text("system.INFORM(")
    version = _ok(acme.get(f"/precondition-sets/{made['id']}@2"))
    first = version["validation"]["blocked"][0]
    expect(marked).to_have_attribute("data-line", str(first["line"]))


@needs_browser
def test_a_rules_exceptions_are_shown_in_the_demonstrations_code(
    page: Page, stack: Stack, keys: tuple[Path, dict[str, str]], acme: httpx.Client, inferred: dict[str, Any]
) -> None:
    line = next(n for n, text in enumerate(DEMOS[0].splitlines(), 1) if text.startswith("system.OFFER("))
    call = DEMOS[0].splitlines()[line - 1]
    evidence = json.loads(json.dumps(inferred["evidence"]))
    evidence["SYSTEM.OFFER"]["self.query_success"] = {  # as a tolerant inference reports a slip in the log
        "occurrences": 20, "holds": 19, "confidence": 0.8, "verdict": "tolerated", "elsewhere": 40,
        "holds_elsewhere": 10, "exceptions": [{"demonstration": 0, "position": 9, "line": line, "call": call}]}
    made = _create(acme, inferred, evidence=evidence)
    assert made["decided"]["SYSTEM.OFFER"]["self.query_success"] == "established"
    _open(page, stack, f"/ui/sets/{made['id']}", keys[1]["acme"])
    item = _rule(page, "SYSTEM.OFFER", "self.query_success")
    expect(item.locator(".evidence")).to_contain_text("held at 19 of 20 demonstrated calls")
    exception = item.locator(".exception")
    expect(exception.locator("figcaption").first).to_contain_text(f"demonstration 0, line {line}")
    expect(exception.locator(".line.marked")).to_have_attribute("data-line", str(line))
    expect(exception.locator(".line.marked")).to_contain_text(call)
    exception.locator("details summary").click()  # the whole demonstration, the same line marked
    expect(exception.locator("details .line")).to_have_count(len(DEMOS[0].rstrip("\n").splitlines()))
    expect(exception.locator("details .line.marked")).to_have_attribute("data-line", str(line))
    # established rules come after the ones that need a human
    labels = page.locator("section.action[data-action='SYSTEM.OFFER'] li.rule").evaluate_all(
        "items => items.map(i => i.dataset.decided)")
    assert labels == sorted(labels, key=lambda label: label == "established")


@needs_browser
def test_an_edit_on_a_stale_page_shows_the_apis_conflict_at_its_rule(
    page: Page, acme: httpx.Client, opened: dict[str, Any]
) -> None:
    made = opened
    rule = made["preconditions"]["SYSTEM.GOODBYE"][0]
    _ok(acme.post(f"/precondition-sets/{made['id']}/versions", json={"edits": [
        {"op": "require", "action": "SYSTEM.GOODBYE", "rule": rule}]}), 201)  # meanwhile, elsewhere
    item = _rule(page, "SYSTEM.GOODBYE", rule)
    item.locator("button[data-op=remove]").click()
    expect(item.locator(".error")).to_contain_text("base_version 1 is not the latest version (2)")
    assert _ok(acme.get(f"/precondition-sets/{made['id']}"))["latest"] == 2


@needs_browser
def test_what_does_not_exist_or_is_not_yours_is_a_not_found_page(
    page: Page, stack: Stack, keys: tuple[Path, dict[str, str]], acme: httpx.Client, inferred: dict[str, Any]
) -> None:
    made = _create(acme, inferred)
    _open(page, stack, f"/ui/sets/{made['id']}@7", keys[1]["acme"])
    expect(page.locator("#not-found")).to_contain_text(f"precondition set {made['id']} has no version 7")
    page.goto(f"{stack.base_url}/ui/sets/ps_{'0' * 24}")
    expect(page.locator("#not-found")).to_contain_text(f"no precondition set ps_{'0' * 24}")
    page.goto(f"{stack.base_url}/ui/sets/not-a-set")
    expect(page.locator("#not-found")).to_contain_text("not a precondition set reference")
    # another tenant (a key of theirs in this tab): word for word the missing set's page
    page.evaluate("sessionStorage.clear()")
    _open(page, stack, f"/ui/sets/{made['id']}", keys[1]["globex"])
    expect(page.locator("#not-found")).to_contain_text(f"no precondition set {made['id']}")


@needs_browser
def test_a_tenants_text_is_shown_never_run(
    page: Page, stack: Stack, keys: tuple[Path, dict[str, str]], acme: httpx.Client
) -> None:
    payload = '<img src=x onerror="document.title=1">'
    demo = DEMOS[0].replace("system = SYSTEM(user)\n", f"system = SYSTEM(user)\nuser.INFORM({payload!r})\n", 1)
    rule = f"self.user is not None and {payload!r} != ''"
    made = _ok(acme.post("/precondition-sets", json={"spec": SPEC, "demonstrations": [demo],
                                                     "preconditions": {"SYSTEM.INFORM": [rule]}}), 201)
    _open(page, stack, f"/ui/sets/{made['id']}", keys[1]["acme"])
    expect(_rule(page, "SYSTEM.INFORM", payload)).to_have_count(1)
    assert page.locator("img").count() == 0 and page.title() != "1"


@needs_browser
def test_an_inference_started_from_the_page_becomes_a_set(
    page: Page, stack: Stack, keys: tuple[Path, dict[str, str]], acme: httpx.Client
) -> None:
    _open(page, stack, "/ui/", keys[1]["acme"])
    request = dict(EXAMPLES["infer-enumerate"], options={"generators": ["enumerate"], "tolerance": 0, "seed": 7})
    page.locator("#infer-request").fill(json.dumps(request))
    page.locator("#infer-start").click()
    page.wait_for_url("**/ui/sets/ps_*@1")
    reference = page.url.rsplit("/", 1)[1]
    stored = _ok(acme.get(f"/precondition-sets/{reference}"))
    assert stored["evidence"] and stored["candidates"] and stored["demonstrations"] == DEMOS
    # the page asks for every candidate (the request's default lists the kept ones): the alternatives are kept
    assert any(not c["kept"] for reports in stored["candidates"].values() for c in reports), stored["candidates"]
    expect(page.locator("section.action")).to_have_count(len(stored["preconditions"]))
    page.goto(f"{stack.base_url}/ui/")
    expect(page.locator(f"#sets tr[data-set='{stored['id']}']")).to_be_visible()
    # pasted spec and demonstrations (a line `# ---` between two), model-free: followed through its job
    page.locator("#infer-spec").fill(SPEC)
    page.locator("#infer-demos").fill(f"{DEMOS[0]}\n# ---\n{DEMOS[1]}")
    page.locator("#infer-model-free").check()
    page.locator("#infer-start").click()
    expect(page.locator("#infer-progress")).to_be_visible()
    page.wait_for_url("**/ui/sets/ps_*@1")
    pasted = _ok(acme.get(f"/precondition-sets/{page.url.rsplit('/', 1)[1]}"))
    assert [d.strip() for d in pasted["demonstrations"]] == [d.strip() for d in DEMOS]
    assert pasted["id"] != stored["id"] and pasted["candidates"]


@needs_browser
@pytest.mark.parametrize("width", [1280, 390])
def test_the_set_page_fits_the_screen(
    chromium: Browser, stack: Stack, keys: tuple[Path, dict[str, str]], acme: httpx.Client,
    inferred: dict[str, Any], width: int
) -> None:
    made = _create(acme, inferred)
    context = chromium.new_context(viewport={"width": width, "height": 800})
    try:
        page = context.new_page()
        _open(page, stack, f"/ui/sets/{made['id']}", keys[1]["acme"])
        expect(page.locator("section.action").first).to_be_visible()
        assert page.evaluate("document.documentElement.scrollWidth") <= width
        assert page.locator("#try-check").bounding_box()["width"] > 0  # type: ignore[index]
    finally:
        context.close()


def test_no_key_reaches_a_log(stack: Stack, keys: tuple[Path, dict[str, str]]) -> None:
    """Last in the module: every key was used by now, through the API and the page."""
    logs = "".join(path.read_text(errors="replace") for path in stack.logs.glob("*.log"))
    assert not [tenant for tenant, key in keys[1].items() if key in logs]


@needs_browser
def test_a_transferred_rule_shows_where_it_was_learned(
    page: Page, stack: Stack, keys: tuple[Path, dict[str, str]], acme: httpx.Client, inferred: dict[str, Any]
) -> None:
    evidence = json.loads(json.dumps(inferred["evidence"]))
    evidence["SYSTEM.OFFER"]["self.query_success"] |= {"decided": "transferred", "source": "ps_buses@3, ps_homes@1"}
    made = _create(acme, inferred, evidence=evidence)
    assert made["decided"]["SYSTEM.OFFER"]["self.query_success"] == "transferred"
    _open(page, stack, f"/ui/sets/{made['id']}", keys[1]["acme"])
    item = _rule(page, "SYSTEM.OFFER", "self.query_success")
    expect(item.locator(".badge").first).to_have_text("transferred")
    expect(item.locator(".source")).to_have_text("from ps_buses@3, ps_homes@1")
