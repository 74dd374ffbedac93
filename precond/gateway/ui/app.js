// The review page's entry: which view the address names, and the key dialog. Each view is its own module.

// Only api.js is imported up front: a set's JSON is requested while the view's modules still load.
import { api, forgetKey, hasKey, setPath, whenKeyNeeded } from "./api.js";

const main = document.getElementById("main");
const forget = document.getElementById("forget");
let servedStatus = document.body.dataset.status;

function navigate(path) {
  history.pushState(null, "", path);
  route();
}

async function notFound(message) {
  const { clear, h } = await import("./dom.js");
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
      await notFound(match ? `${decodeURIComponent(match[1])} is not a precondition set reference (ps_… or ps_…@n).`
        : `There is no page at ${path}.`);
    } else if (path === "/ui/") {
      const { listPage } = await import("./list.js");
      await listPage(main, navigate);
    } else if (match) {
      const answer = api("GET", setPath(decodeURIComponent(match[1])));
      answer.catch(() => {});  // settled by the view
      const { setPage } = await import("./set.js");
      await setPage(main, answer, navigate, notFound);
    } else {
      await notFound(`There is no page at ${path}.`);
    }
  } catch (error) {
    const { clear, h } = await import("./dom.js");
    clear(main, h("section", { class: "card" }, h("h1", {}, "The service refused"),
      h("p", { class: "error" }, error.message)));
  }
  forget.hidden = !hasKey();
}

async function askKey(message) {
  const { h } = await import("./dom.js");
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
