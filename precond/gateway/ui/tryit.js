// Try a version: an event history (actor, act, args; typed row by row, or pasted as JSON: events or an agent's
// OpenAI messages) and a few calls, judged by /check-actions with this version's rules. Arguments stay literals:
// a word is a string, JSON scalars (2, true, null, "a, b") are values. A judged call the reviewer disagrees with
// ("this should have been refused", or allowed) becomes a counterexample of the set: the API re-infers the call's
// action with it, and the page opens the new version.

import { api, follow, setPath } from "./api.js";
import { clear, errorBox, h } from "./dom.js";

export function tryPanel(set, navigate) {
  const { actors, acts } = vocabulary(set.spec);
  const events = h("div", { class: "events", id: "try-events" });
  const pasted = h("textarea", { id: "try-json", "aria-label": "history as JSON",
    placeholder: '[{"actor": "user", "act": "INFORM", "args": ["city"]}, ...] or [{"role": "user", ...}, ...]' });
  const calls = h("textarea", { id: "try-calls", placeholder: "system.REQUEST('city')\none call per line" });
  const results = h("div", { id: "try-results" });
  const error = h("div", { class: "error", role: "alert", hidden: true, id: "try-error" });
  const addEvent = () => events.append(eventRow());

  async function check(event) {
    event.preventDefault();
    error.hidden = true;
    clear(results);
    let body;
    try {
      const history = pasted.value.trim() ? readPasted(pasted.value) : [...events.children].map(readEvent);
      body = { precondition_set: set.reference, history,
        calls: calls.value.split("\n").map((c) => c.trim()).filter(Boolean) };
      if (!body.calls.length) throw new Error("write at least one call");
      const verdicts = await follow(await api("POST", "/check-actions?wait=10", body));
      const label = (result) => counterexampleButton(set, body.history, result, error, navigate);
      clear(results, [verdicts.history_violation
        ? h("p", { class: "banner bad", id: "try-history-violation" }, `The history already broke a rule: `
          + verdicts.history_violation) : null, ...verdicts.results.map((r) => verdict(r, label(r)))]);
    } catch (problem) {
      errorBox(error, problem);
    }
  }

  addEvent();
  return h("section", { class: "card", id: "try" },
    h("h2", {}, "Try it"),
    h("p", { class: "muted" }, `What happened (events), then calls to judge with ${set.reference}.`),
    h("datalist", { id: "try-actors" }, actors.map((a) => h("option", { value: a }))),
    h("datalist", { id: "try-acts" }, acts.map((a) => h("option", { value: a }))),
    h("form", { onsubmit: check }, events,
      h("div", { class: "row" }, h("button", { type: "button", id: "try-add-event", onclick: addEvent }, "+ event")),
      h("label", { class: "block", for: "try-json" }, "or paste the history as JSON (events or OpenAI messages; "
        + "used instead of the rows)"), pasted,
      h("label", { class: "block", for: "try-calls" }, "Calls"), calls,
      h("div", { class: "row" }, h("button", { class: "primary", type: "submit", id: "try-check" }, "Check"))),
    error, results);
}

function eventRow() {
  const row = h("div", { class: "event" },
    h("input", { name: "actor", placeholder: "actor", list: "try-actors", "aria-label": "actor" }),
    h("input", { name: "act", placeholder: "act", list: "try-acts", "aria-label": "act" }),
    h("input", { name: "args", placeholder: "args: city, 2", "aria-label": "arguments" }),
    h("button", { type: "button", "aria-label": "remove event", onclick: () => row.remove() }, "×"));
  return row;
}

function readEvent(row, index) {
  const value = (name) => row.querySelector(`[name=${name}]`).value.trim();
  if (!value("actor") || !value("act")) throw new Error(`event ${index + 1}: give its actor and act`);
  return { actor: value("actor"), act: value("act"), args: parseArgs(value("args")) };
}

/** A pasted history: a JSON list of events or of OpenAI messages, sent as it is (the API checks each item). */
function readPasted(text) {
  let value;
  try {
    value = JSON.parse(text);
  } catch (problem) {
    throw new Error(`pasted history: not JSON (${problem.message})`);
  }
  if (value && !Array.isArray(value) && Array.isArray(value.messages)) value = value.messages;  // a logged run
  if (!Array.isArray(value)) throw new Error("pasted history: give a JSON list of events or of OpenAI messages");
  return value;
}

function parseArgs(text) {
  if (!text) return [];
  try {
    const values = JSON.parse(`[${text}]`);
    if (values.every((v) => v === null || ["string", "number", "boolean"].includes(typeof v))) return values;
  } catch { /* words, not JSON: each comma-separated part is a string */ }
  return text.split(",").map((part) => part.trim());
}

/** What a verdict rests on (`rule_status`), in words: "allowed" means little when nothing is known. */
const STATUS_WORDS = {
  established: "the demonstrations show its rule",
  assumed: "its rule is assumed: review it",
  transferred: "its rule is transferred from other services",
  "zero-shot": "its rule is the code model's guess: review it",
  missing: "no rule learned: nothing is known about this action",
  given: "its rule was given, not learned",
};

/** "This should have been refused" on an allowed call of an action (or "allowed" on a refused one): records the
 * history and the call as a counterexample (`POST /precondition-sets/{id}/counterexamples`, a re-inference job
 * of the call's action) and opens the version it makes. Only on the latest version: the API says 409 otherwise. */
function counterexampleButton(set, history, result, error, navigate) {
  if (!result.action || set.version !== set.latest) return null;
  const wanted = result.allowed ? "refuse" : "allow";
  const button = h("button", { type: "button", class: "counterexample", dataset: { verdict: wanted } },
    result.allowed ? "this should have been refused" : "this should have been allowed");
  button.onclick = async () => {
    button.disabled = true;
    button.textContent = "re-inferring…";
    error.hidden = true;
    try {
      const made = await follow(await api("POST", `${setPath(set.id)}/counterexamples?wait=60`,
        { history, call: result.call, verdict: wanted, base_version: set.version }));
      navigate(`/ui/sets/${made.reference}`);
    } catch (problem) {
      button.disabled = false;
      button.textContent = result.allowed ? "this should have been refused" : "this should have been allowed";
      errorBox(error, problem);
    }
  };
  return h("div", {}, button);
}

function verdict(result, label) {
  const allowed = result.allowed;
  const status = result.rule_status;
  return h("div", { class: `verdict ${allowed ? "allowed" : "refused"}`,
    dataset: { call: result.call, status: status || "" } },
    h("strong", {}, allowed ? "allowed" : "refused"), " ", h("code", {}, result.call),
    status ? [" ", h("span", { class: `badge d-${status}`, title: STATUS_WORDS[status] || status }, status),
      h("div", { class: "status" }, STATUS_WORDS[status] || status)] : null,
    result.violations.length ? h("div", {}, "violates: ", result.violations.map((v, i) => [i ? ", " : "",
      h("code", {}, v)])) : null,
    result.error ? h("div", {}, result.error) : null, label);
}

/** Suggestions only (the API judges every event): the spec's classes as actors and its methods as acts. */
function vocabulary(spec) {
  const actors = [...spec.matchAll(/^class\s+(\w+)/gm)].map((m) => m[1].toLowerCase());
  const acts = [...new Set([...spec.matchAll(/^\s+def\s+([A-Za-z]\w*)\s*\(/gm)].map((m) => m[1]))];
  return { actors, acts };
}
