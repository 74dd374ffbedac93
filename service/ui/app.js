// The review page's entry: which view the address names, and the key dialog. Each view is its own module.

import { forgetKey, hasKey, whenKeyNeeded } from "./api.js";
import { clear, h } from "./dom.js";
import { listPage } from "./list.js";
import { setPage } from "./set.js";

const main = document.getElementById("main");
const forget = document.getElementById("forget");
let servedStatus = document.body.dataset.status;

export function navigate(path) {
  history.pushState(null, "", path);
  route();
}

export function notFound(message) {
  document.title = "Not found · precondition sets";
  clear(main, h("section", { class: "card", id: "not-found" },
    h("h1", {}, "Not found (404)"), h("p", {}, message), h("p", {}, h("a", { href: "/ui/" }, "All precondition sets"))));
}

async function route() {
  const status = servedStatus;
  servedStatus = undefined;  // the served status is the first address's only
  const path = location.pathname;
  const match = path.match(/^\/ui\/sets\/([^/]+)$/);
  try {
    if (status === "404") {
      notFound(match ? `${decodeURIComponent(match[1])} is not a precondition set reference (ps_… or ps_…@n).`
        : `There is no page at ${path}.`);
    } else if (path === "/ui/") {
      await listPage(main, navigate);
    } else if (match) {
      await setPage(main, decodeURIComponent(match[1]), navigate, notFound);
    } else {
      notFound(`There is no page at ${path}.`);
    }
  } catch (error) {
    clear(main, h("section", { class: "card" }, h("h1", {}, "The service refused"),
      h("p", { class: "error" }, error.message)));
  }
  forget.hidden = !hasKey();
}

function askKey(message) {
  return new Promise((resolve) => {
    const input = h("input", { type: "password", autocomplete: "off", name: "key", placeholder: "pk_…",
      "aria-label": "API key", required: true });
    const back = h("div", { class: "dialog-back" }, h("form", {
      class: "dialog", id: "key-dialog",
      onsubmit: (event) => { event.preventDefault(); back.remove(); resolve(input.value.trim()); },
    },
    h("h2", {}, "API key"),
    h("p", { class: "muted" }, message || "This service needs an API key."),
    h("p", { class: "muted" }, "Kept in this tab only, sent as a Bearer header."),
    input, h("button", { class: "primary", type: "submit" }, "Use this key")));
    document.body.append(back);
    input.focus();
  });
}

whenKeyNeeded(askKey);
forget.addEventListener("click", () => { forgetKey(); location.reload(); });
window.addEventListener("popstate", route);
route();
