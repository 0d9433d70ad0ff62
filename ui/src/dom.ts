// A tiny DOM helper (the screens are small; no UI framework).
export type Attrs = Record<string, string | number | boolean | ((ev: Event) => void)>;

export function h<K extends keyof HTMLElementTagNameMap>(tag: K, attrs: Attrs = {}, ...kids: (Node | string)[]): HTMLElementTagNameMap[K] {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    // A listener: `onclick` or `click` (two screens wrote the latter, and slicing it made
    // "ick": their rows could not be selected by a tap).
    if (typeof v === "function") el.addEventListener(k.startsWith("on") ? k.slice(2) : k, v);
    else if (typeof v === "boolean") { if (v) el.setAttribute(k, ""); }
    else el.setAttribute(k, String(v));
  }
  for (const c of kids) el.append(c);
  return el;
}

/** A table with a header row; every cell is text. */
export function table(head: string[], rows: string[][], testid?: string): HTMLTableElement {
  const t = h("table", { class: "table", ...(testid ? { "data-testid": testid } : {}) });
  t.append(h("thead", {}, h("tr", {}, ...head.map((c) => h("th", {}, c)))));
  t.append(h("tbody", {}, ...rows.map((r) => h("tr", {}, ...r.map((c) => h("td", {}, c))))));
  return t;
}
