// Building the page: every string becomes a text node (never markup), so a rule, a demonstration or an error
// message is shown as written whatever it contains.

export function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs || {})) {
    if (value === undefined || value === null || value === false) continue;
    if (name.startsWith("on")) el.addEventListener(name.slice(2), value);
    else if (name === "class") el.className = value;
    else if (name === "dataset") Object.assign(el.dataset, value);
    else if (name === "value" || name === "checked") el[name] = value;
    else el.setAttribute(name, value === true ? "" : String(value));
  }
  return add(el, children);
}

export function add(el, children) {
  for (const child of children.flat(Infinity)) {
    if (child === undefined || child === null || child === false) continue;
    el.append(child instanceof Node ? child : String(child));
  }
  return el;
}

export function clear(el, ...children) {
  el.replaceChildren();
  return add(el, children);
}

/** A <details> whose body is built the first time it is opened: long lists cost nothing until read. */
export function lazyDetails(summary, build, attrs) {
  const details = h("details", attrs, h("summary", {}, summary));
  details.addEventListener("toggle", () => {
    if (details.open && !details.dataset.built) {
      details.dataset.built = "1";
      add(details, [build()]);
    }
  });
  return details;
}

/** Lines of a program with one line marked, `context` lines either side (all of them when null). */
export function code(source, line, caption, context = 3) {
  const lines = source.split("\n");
  if (lines.length && lines[lines.length - 1] === "") lines.pop();
  const from = context === null ? 1 : Math.max(1, line - context);
  const to = context === null ? lines.length : Math.min(lines.length, line + context);
  const rows = [];
  for (let n = from; n <= to; n++) {
    rows.push(h("span", { class: n === line ? "line marked" : "line", dataset: { line: n } },
      h("span", { class: "no" }, n), lines[n - 1]));
  }
  return h("figure", { class: "code" }, h("figcaption", {}, caption), h("pre", {}, rows));
}

export function errorBox(slot, error, ...more) {
  clear(slot, error.message, ...more);
  slot.hidden = false;
}

/** A link that changes the view without reloading the page (a plain click; others open as usual). */
export function linkTo(navigate, path) {
  return (event) => {
    if (event.button === 0 && !event.ctrlKey && !event.metaKey && !event.shiftKey) {
      event.preventDefault();
      navigate(path);
    }
  };
}

/** An ISO time as the page shows it: "2026-11-24 08:36 UTC". */
export function when(iso) {
  return `${iso.slice(0, 10)} ${iso.slice(11, 16)} UTC`;
}
