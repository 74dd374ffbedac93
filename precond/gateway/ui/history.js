// The versions of a set, what made each one (edits, a re-inference), and the rules that differ between two.

import { api, setPath } from "./api.js";
import { clear, h, lazyDetails, linkTo, when } from "./dom.js";

export function historyPanel(set, navigate) {
  return h("section", { class: "card", id: "history" }, h("h2", {}, "Versions"),
    lazyDetails(`history of ${set.latest} version${set.latest === 1 ? "" : "s"}, and differences`,
      () => historyBody(set, navigate), { id: "history-details" }));
}

function historyBody(set, navigate) {
  const body = h("div", {}, h("p", { class: "muted" }, "Loading versions…"));
  const numbers = Array.from({ length: set.latest }, (_, i) => set.latest - i);
  Promise.all(numbers.map((n) => api("GET", setPath(`${set.id}@${n}`)).then((a) => a.body)))
    .then((versions) => clear(body, versionList(versions, navigate), diffForm(versions, set.version)))
    .catch((problem) => clear(body, h("p", { class: "error" }, problem.message)));
  return body;
}

function versionList(versions, navigate) {
  return h("ol", { reversed: true, id: "versions" }, versions.map((v) => h("li", {},
    h("a", { href: `/ui/sets/${v.reference}`, onclick: linkTo(navigate, `/ui/sets/${v.reference}`) }, `v${v.version}`),
    " ", h("span", { class: "muted" }, when(v.created)), " · ", madeBy(v))));
}

function madeBy(version) {
  if (version.edits.length) return version.edits.map((e) => `${e.op} ${e.action}: ${e.rule}`).join("; ");
  if (version.diff) {
    return `re-inference (+${version.diff.added.length} −${version.diff.removed.length}, `
      + `${version.diff.new_demonstrations} new demonstrations)`;
  }
  return "created";
}

function diffForm(versions, current) {
  const byNumber = new Map(versions.map((v) => [v.version, v]));
  const pick = (id, chosen) => h("select", { id, "aria-label": id }, versions.map((v) =>
    h("option", { value: v.version, selected: v.version === chosen }, `v${v.version}`)));
  const from = pick("diff-from", Math.max(1, current - 1));
  const to = pick("diff-to", current);
  const out = h("div", { class: "diff", id: "diff" });
  const show = () => clear(out, diff(byNumber.get(Number(from.value)), byNumber.get(Number(to.value))));
  from.addEventListener("change", show);
  to.addEventListener("change", show);
  show();
  return h("div", {}, h("h3", {}, "Difference"), h("div", { class: "row" }, from, "→", to), out);
}

function pairs(table) {
  return new Set(Object.entries(table || {}).flatMap(([a, rules]) => rules.map((r) => `${a}\u0000${r}`)));
}

/** Why a rule came or went, where `newer` is the re-inference of `older` (its `diff` says). */
function reasons(older, newer) {
  const why = new Map();
  if (newer.diff && newer.diff.base_version === older.version) {
    for (const change of [...newer.diff.added, ...newer.diff.removed]) {
      if (change.reason) why.set(`${change.action}\u0000${change.rule}`, change.reason);
    }
  }
  return why;
}

function diff(older, newer) {
  const lines = [];
  const why = reasons(older, newer);
  const compare = (part, plus, minus) => {
    const before = pairs(older[part]);
    const after = pairs(newer[part]);
    for (const p of after) if (!before.has(p)) lines.push([plus, p]);
    for (const p of before) if (!after.has(p)) lines.push([minus, p]);
  };
  compare("preconditions", "added", "removed");
  compare("required", "marked required", "no longer required");
  compare("rejected", "marked rejected", "no longer rejected");
  if (!lines.length) return h("p", { class: "muted" }, `v${older.version} and v${newer.version} have the same rules.`);
  return h("ul", {}, lines.map(([what, pair]) => {
    const [action, rule] = pair.split("\u0000");
    return h("li", { class: what === "added" ? "added" : what === "removed" ? "removed" : "" },
      `${what}: ${action} `, h("code", {}, rule), why.has(pair) ? h("div", { class: "reason" }, why.get(pair)) : null);
  }));
}
