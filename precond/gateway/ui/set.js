// One version of a set, per action: its rules (how each was decided, its evidence, its exceptions in the
// demonstration's own code), the alternatives the learner dropped and why, and the actions with no rule.
// Edits make a new version through the API; what it refuses is shown at the rule it concerns.

import { ApiError, api, setPath } from "./api.js";
import { add, clear, code, errorBox, h, lazyDetails, linkTo, when } from "./dom.js";
import { historyPanel } from "./history.js";
import { tryPanel } from "./tryit.js";

const NEEDS_HUMAN = ["assumed", "zero-shot"];
const ORDER = ["assumed", "zero-shot", "no evidence", "transferred", "validated", "established"];

/** `answer`: the API's answer for the set, requested before this module was loaded. */
export async function setPage(main, answer, navigate, notFound) {
  let set;
  try {
    set = (await answer).body;
  } catch (problem) {
    if (problem instanceof ApiError && problem.status === 404) return notFound(`${problem.message}.`);
    throw problem;
  }
  document.title = `${set.reference} · precondition sets`;
  clear(main, render(set, navigate));
  performance.mark("rendered");
}

/** How a rule was decided, as the service stored it with the version (`decided`). */
const decidedOf = (set, action, rule) => ((set.decided || {})[action] || {})[rule] || "no evidence";
const rank = (label) => (ORDER.includes(label) ? ORDER.indexOf(label) : ORDER.length);
const canonical = (text) => text.replace(/\s+/g, " ").trim();

function lookup(table, rule) {
  if (!table) return undefined;
  if (rule in table) return table[rule];
  const wanted = canonical(rule);
  const key = Object.keys(table).find((k) => canonical(k) === wanted);
  return key === undefined ? undefined : table[key];
}

function render(set, navigate) {
  const editable = set.version === set.latest;
  const actions = [...new Set([...Object.keys(set.preconditions), ...Object.keys(set.candidates || {}),
    ...Object.keys(set.warnings || {}), ...Object.keys(set.rejected || {})])];
  const withRules = actions.filter((a) => (set.preconditions[a] || []).length)
    .map((a) => ({ action: a, rules: [...set.preconditions[a]].sort((x, y) =>
      rank(decidedOf(set, a, x)) - rank(decidedOf(set, a, y))) }))
    .sort((x, y) => rank(decidedOf(set, x.action, x.rules[0])) - rank(decidedOf(set, y.action, y.rules[0]))
      || x.action.localeCompare(y.action));
  const without = actions.filter((a) => !(set.preconditions[a] || []).length).sort();
  const labels = withRules.flatMap(({ action, rules }) => rules.map((r) => decidedOf(set, action, r)));
  const review = labels.filter((l) => NEEDS_HUMAN.includes(l)).length;

  const edit = async (edits, force, slot) => {
    slot.hidden = true;
    try {
      const made = (await api("POST", `${setPath(set.id)}/versions`,
        { edits, base_version: set.version, force })).body;
      navigate(`/ui/sets/${made.reference}`);
    } catch (problem) {
      const blocks = problem instanceof ApiError && problem.type === "blocks_demonstration";
      const retry = blocks && !force
        ? h("button", { type: "button", class: "danger force", onclick: () => edit(edits, true, slot) },
          "Keep it anyway (force)") : null;
      const blocked = blocks ? h("ul", { class: "blocked" }, ...problem.blocked.map((b) => h("li", {},
        `demonstrations[${b.demonstration}], line ${b.line}: ${b.call} — blocked by ${b.action}: ${b.rule}`)))
        : " ";
      errorBox(slot, problem, blocked, retry);
    }
  };

  return h("div", {},
    h("section", { class: "card", id: "set-head" },
      h("h1", {}, set.id),
      h("div", { class: "meta" },
        h("span", {}, `version ${set.version} of ${set.latest}`),
        h("span", { class: "muted" }, when(set.created)),
        versionPicker(set, navigate),
        h("span", {}, `${labels.length} rules`),
        h("span", { class: review || without.length ? "badge d-zero-shot" : "badge d-established",
          id: "review-count" }, `${review} need${review === 1 ? "s" : ""} a human`),
        without.length ? h("a", { class: "badge d-no-evidence", id: "no-rule-count", href: "#no-rule" },
          `${without.length} action${without.length === 1 ? "" : "s"} without a rule: every call allowed`) : null),
      editable ? null : h("p", { class: "banner" }, `This is version ${set.version}; edits make a new version from `
        + "the latest. ", h("a", { href: `/ui/sets/${set.id}`, onclick: linkTo(navigate, `/ui/sets/${set.id}`) },
        `Open version ${set.latest}`)),
      blockedBanner(set)),
    h("div", { class: "layout" },
      h("div", { id: "actions" },
        withRules.map(({ action, rules }) => actionCard(set, action, rules, editable, edit)),
        without.length ? h("section", { class: "card", id: "no-rule" }, h("h2", {}, "Actions with no rule"),
          h("ul", { class: "rules" }, without.map((a) => h("li", { class: "rule", dataset: { action: a } },
            h("div", { class: "rule-head" }, h("code", {}, a)), h("p", { class: "reason" }, whyNoRule(set, a)),
            rejectedList(set, a), dropped(set, a, editable, edit), addForm(a, editable, edit))))) : null),
      h("aside", {}, tryPanel(set, navigate), historyPanel(set, navigate))));
}

function versionPicker(set, navigate) {
  const options = [];
  for (let n = set.latest; n >= 1; n--) options.push(h("option", { value: n, selected: n === set.version }, `v${n}`));
  return h("select", { "aria-label": "version", id: "version",
    onchange: (event) => navigate(`/ui/sets/${set.id}@${event.target.value}`) }, options);
}

function blockedBanner(set) {
  const blocked = (set.validation && set.validation.blocked) || [];
  if (!blocked.length) return null;
  return h("p", { class: "banner bad" }, `Stored with force: ${blocked.length} demonstrated call`
    + `${blocked.length === 1 ? "" : "s"} would be refused by these rules (shown at each rule).`);
}

function actionCard(set, action, rules, editable, edit) {
  return h("section", { class: "card action", dataset: { action } },
    h("h2", {}, action),
    (set.warnings || {})[action] ? h("p", { class: "banner" }, set.warnings[action]) : null,
    h("ul", { class: "rules" }, rules.map((rule) => ruleItem(set, action, rule, editable, edit))),
    rejectedList(set, action), dropped(set, action, editable, edit), addForm(action, editable, edit));
}

function ruleItem(set, action, rule, editable, edit) {
  const label = decidedOf(set, action, rule);
  const evidence = lookup((set.evidence || {})[action], rule);
  const report = ((set.candidates || {})[action] || []).find((c) => canonical(c.assertion) === canonical(rule));
  const required = ((set.required || {})[action] || []).includes(rule);
  const slot = h("div", { class: "error", role: "alert", hidden: true });
  const button = (op, text, extra) => h("button", { type: "button", class: extra, disabled: !editable,
    dataset: { op }, onclick: () => edit([{ op, action, rule }], false, slot) }, text);
  const blocked = ((set.validation && set.validation.blocked) || []).filter((b) => b.action === action
    && canonical(b.rule) === canonical(rule));
  return h("li", { class: "rule", dataset: { rule, decided: label } },
    h("div", { class: "rule-head" },
      h("code", {}, rule),
      h("span", { class: `badge d-${label.replace(/\s+/g, "-")}`, title: "how it was decided" }, label),
      evidence && evidence.source ? h("span", { class: "source", title: "where the prior rule was learned" },
        `from ${evidence.source}`) : null,
      required ? h("span", { class: "badge required" }, "required") : null,
      h("span", { class: "buttons" },
        required ? null : button("require", "Require"), button("reject", "Reject", "danger"),
        button("remove", "Remove"))),
    report && report.reason ? h("p", { class: "reason" }, report.kept ? "" : "The learner dropped it: ",
      report.reason) : null,
    evidenceLine(evidence),
    evidence && (evidence.refuses || []).length ? h("p", { class: "refuses" }, "refuses the counterexamples: ",
      evidence.refuses.map((name, i) => [i ? ", " : "", h("code", {}, name)])) : null,
    evidence && (evidence.refuses_allowed || []).length ? h("p", { class: "refuses-allowed bad" },
      "refuses calls labelled allowed: ", evidence.refuses_allowed.map((name, i) => [i ? ", " : "",
        h("code", {}, name)])) : null,
    evidence ? evidence.exceptions.map((e) => exceptionCode(set, e, "exception")) : null,
    blocked.map((b) => exceptionCode(set, b, "would refuse")),
    slot);
}

function evidenceLine(evidence) {
  if (!evidence) {
    return h("p", { class: "evidence muted" }, "No evidence: written by hand, or stored without an inference's "
      + "report.");
  }
  const elsewhere = evidence.elsewhere ? `; true at ${evidence.holds_elsewhere} of ${evidence.elsewhere} other `
    + "points" : "";
  return h("p", { class: "evidence" },
    `held at ${evidence.holds} of ${evidence.occurrences} demonstrated call${evidence.occurrences === 1 ? "" : "s"}`
    + `${elsewhere} · confidence ${evidence.confidence.toFixed(2)} · ${evidence.verdict}`);
}

function exceptionCode(set, where, what) {
  const source = set.demonstrations[where.demonstration];
  const caption = `${what}: demonstration ${where.demonstration}, line ${where.line}`
    + (where.call ? ` (${where.call})` : "");
  if (source === undefined || !where.line) return h("p", { class: "muted" }, caption);
  return h("div", { class: "exception" }, code(source, where.line, caption),
    lazyDetails("whole demonstration", () => code(source, where.line, `demonstration ${where.demonstration}`, null)));
}

function whyNoRule(set, action) {
  if ((set.warnings || {})[action]) return set.warnings[action];
  if (((set.rejected || {})[action] || []).length) return "Its rules were rejected by hand: every call of it is allowed.";
  const candidates = (set.candidates || {})[action] || [];
  if (candidates.some((c) => c.kept)) return "Its learned rules were removed by hand: every call of it is allowed.";
  if (candidates.length) return `The learner kept none of its ${candidates.length} candidates (below, with why).`;
  return "No rule: every call of it is allowed.";
}

function rejectedList(set, action) {
  const rejected = (set.rejected || {})[action] || [];
  if (!rejected.length) return null;
  return h("p", { class: "muted rejected" }, "Rejected (kept out of re-inference): ",
    rejected.map((r, i) => [i ? ", " : "", h("code", {}, r)]));
}

function dropped(set, action, editable, edit) {
  const alternatives = ((set.candidates || {})[action] || []).filter((c) => !c.kept);
  if (!alternatives.length) return null;
  return lazyDetails(`${alternatives.length} alternative${alternatives.length === 1 ? "" : "s"} the learner dropped`,
    () => h("ul", { class: "dropped" }, alternatives.map((c) => {
      const slot = h("div", { class: "error", role: "alert", hidden: true });
      return h("li", { dataset: { rule: c.assertion } }, h("code", {}, c.assertion), " ",
        h("button", { type: "button", disabled: !editable,
          onclick: () => edit([{ op: "add", action, rule: c.assertion }], false, slot) }, "Add"),
        h("div", { class: "reason" }, c.reason || "dropped"), slot);
    })), { class: "alternatives" });
}

function addForm(action, editable, edit) {
  const input = h("input", { name: "rule", placeholder: "a rule, e.g. self.user.informed_slot[slot]",
    "aria-label": `new rule for ${action}`, disabled: !editable, required: true });
  const slot = h("div", { class: "error", role: "alert", hidden: true });
  return add(h("form", { class: "inline add-rule", onsubmit: (event) => {
    event.preventDefault();
    edit([{ op: "add", action, rule: input.value.trim() }], false, slot);
  } }), [input, h("button", { type: "submit", disabled: !editable }, "Add rule"), slot]);
}
