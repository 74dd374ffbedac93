// The tenant's precondition sets, newest first, with what needs a human in each; and a new set from an inference.

import { api } from "./api.js";
import { clear, h, linkTo, when } from "./dom.js";
import { inferPanel } from "./infer.js";

const PAGE = 20;

export async function listPage(main, navigate, offset = 0) {
  document.title = "Precondition sets";
  const page = (await api("GET", `/precondition-sets?offset=${offset}&limit=${PAGE}`)).body;
  const rows = page.sets.map((s) => h("tr", { dataset: { set: s.id } },
    h("td", {}, h("a", { href: `/ui/sets/${s.id}`, onclick: linkTo(navigate, `/ui/sets/${s.id}`) }, s.id)),
    h("td", { class: "num" }, s.latest),
    h("td", { class: "nowrap" }, when(s.updated)),
    h("td", { class: "actions", title: s.actions.join(", ") }, `${s.actions.length}: `,
      s.actions.slice(0, 3).join(", "), s.actions.length > 3 ? ", …" : ""),
    h("td", { class: "num" }, s.rules),
    h("td", { class: "num" }, s.assumed),
    h("td", { class: "num" }, s.zero_shot),
    h("td", { class: "num" }, s.no_evidence)));
  const table = page.sets.length
    ? h("div", { class: "table-wrap" }, h("table", { id: "sets" },
      h("thead", {}, h("tr", {}, h("th", {}, "set"), h("th", { class: "num" }, "version"), h("th", {}, "updated"),
        h("th", {}, "actions"), h("th", { class: "num" }, "rules"), h("th", { class: "num" }, "assumed"),
        h("th", { class: "num" }, "zero-shot"), h("th", { class: "num" }, "no evidence"))),
      h("tbody", {}, rows)))
    : h("p", { class: "muted" }, "No precondition sets yet: store one through the API, or infer one below.");
  const pager = h("div", { class: "row" },
    offset > 0 ? h("button", { onclick: () => listPage(main, navigate, Math.max(0, offset - PAGE)) }, "Newer") : null,
    page.next_offset !== null
      ? h("button", { onclick: () => listPage(main, navigate, page.next_offset) }, "Older") : null,
    h("span", { class: "muted" }, `${page.total} set${page.total === 1 ? "" : "s"}`));
  clear(main,
    h("section", { class: "card" }, h("h1", {}, "Precondition sets"),
      h("p", { class: "muted" }, "Assumed and zero-shot rules are the ones the demonstrations did not settle: "
        + "read them first."), table, pager),
    inferPanel(navigate));
}
