// A new set from an inference: spec and demonstrations (pasted or uploaded), or a converted request.json;
// the job's progress as a bar; the result stored with its evidence and candidates as version 1 of a set.

import { ApiError, api, follow } from "./api.js";
import { clear, errorBox, h } from "./dom.js";

const SEPARATOR = /^# ---+\s*$/m;

export function inferPanel(navigate) {
  const request = h("textarea", { id: "infer-request", placeholder: '{"spec": "...", "demonstrations": [...]}' });
  const spec = h("textarea", { id: "infer-spec", placeholder: "class USER: ..." });
  const demos = h("textarea", { id: "infer-demos", placeholder: "user = USER()\n...\n# ---\nuser = USER()\n..." });
  const modelFree = h("input", { type: "checkbox", id: "infer-model-free" });
  const bar = h("progress", { id: "infer-progress", max: 1, value: 0, hidden: true });
  const phase = h("p", { class: "muted", id: "infer-phase" });
  const error = h("div", { class: "error", id: "infer-error", role: "alert", hidden: true });
  const start = h("button", { class: "primary", type: "submit", id: "infer-start" }, "Infer and store as a set");
  const cancel = h("button", { type: "button", hidden: true }, "Cancel");
  let job = null;

  cancel.addEventListener("click", () => job && api("DELETE", `/jobs/${job}`).catch(() => {}));

  async function run(event) {
    event.preventDefault();
    error.hidden = true;
    let body;
    try {
      body = requestBody(request.value, spec.value, demos.value, modelFree.checked);
    } catch (problem) {
      return errorBox(error, problem);
    }
    start.disabled = true;
    bar.hidden = false;
    bar.removeAttribute("value");  // indeterminate until the job reports
    clear(phase, "queued");
    try {
      // every candidate, so that the stored set offers the dropped ones as alternatives (the default is "kept")
      const asked = { ...body, options: { ...(body.options || {}), candidates: "all" } };
      const first = await api("POST", "/infer-preconditions?wait=0", asked);
      job = first.headers.get("X-Job-Id");
      cancel.hidden = first.status !== 202;
      const result = await follow(first, (status) => {
        const { phase: name, done, total } = status.progress;
        if (total > 0) { bar.max = total; bar.value = done; }
        clear(phase, `${status.status}: ${name}${total ? ` (${done} of ${total})` : ""}`);
      });
      clear(phase, "inferred; storing…");
      await store(body, result, false);
    } catch (problem) {
      errorBox(error, problem);
    } finally {
      start.disabled = false;
      cancel.hidden = true;
    }
  }

  async function store(body, result, force) {
    const set = { spec: body.spec, demonstrations: body.demonstrations, preconditions: result.preconditions,
      evidence: result.evidence, candidates: result.candidates, warnings: result.warnings, force };
    try {
      const made = (await api("POST", "/precondition-sets", set)).body;
      navigate(`/ui/sets/${made.reference}`);
    } catch (problem) {
      if (!(problem instanceof ApiError) || problem.type !== "blocks_demonstration") throw problem;
      // the ways out: keep the rules (the calls they block become their known exceptions, right for labelled
      // calls to refuse), or store the set without the rules that block
      const blocking = new Set(problem.blocked.map((b) => `${b.action}\n${b.rule}`));
      const without = { ...result, preconditions: Object.fromEntries(Object.entries(result.preconditions)
        .map(([action, rules]) => [action, rules.filter((r) => !blocking.has(`${action}\n${r}`))])) };
      const again = (answer, force) => () => store(body, answer, force).catch((e) => errorBox(error, e));
      errorBox(error, problem, h("ul", { id: "infer-blocked" }, ...problem.blocked.map((b) => h("li", {},
        `demonstrations[${b.demonstration}], line ${b.line}: ${b.call} — blocked by ${b.action}: ${b.rule}`))),
      h("button", { type: "button", id: "infer-force", onclick: again(result, true) }, "Store anyway"), " ",
      h("button", { type: "button", id: "infer-without", onclick: again(without, false) },
        "Store without these rules"));
    }
  }

  return h("section", { class: "card", id: "infer" },
    h("h2", {}, "New set from an inference"),
    h("form", { onsubmit: run },
      h("label", { class: "block", for: "infer-request" }, "request.json (from precond convert, or an "
        + "/infer-preconditions body)"),
      fileInto(request, false), request,
      h("p", { class: "muted" }, "or"),
      h("label", { class: "block", for: "infer-spec" }, "Spec"), fileInto(spec, false), spec,
      h("label", { class: "block", for: "infer-demos" }, "Demonstrations (separated by a line # ---)"),
      fileInto(demos, true), demos,
      h("label", { class: "row" }, modelFree, "model-free (enumerate only: about a second, no code model)"),
      h("div", { class: "row" }, start, cancel), bar, phase, error));
}

/** A file picker that puts the files' text into `area` (several files: joined by the separator). */
function fileInto(area, several) {
  return h("input", { type: "file", multiple: several, "aria-label": `upload into ${area.id}`,
    onchange: async (event) => {
      const texts = await Promise.all([...event.target.files].map((file) => file.text()));
      area.value = texts.join("\n# ---\n");
    } });
}

function requestBody(requestText, specText, demosText, modelFree) {
  let body;
  if (requestText.trim()) {
    try {
      body = JSON.parse(requestText);
    } catch (problem) {
      throw new Error(`request.json is not JSON: ${problem.message}`);
    }
  } else {
    if (!specText.trim() || !demosText.trim()) throw new Error("give a request.json, or a spec and demonstrations");
    body = { spec: specText, demonstrations: demosText.split(SEPARATOR).map((d) => d.trim() + "\n")
      .filter((d) => d.trim()) };
  }
  if (modelFree) body.options = { ...(body.options || {}), generators: ["enumerate"] };
  return body;
}
