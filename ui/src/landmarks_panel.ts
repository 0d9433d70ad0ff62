// The "Cortical landmarks" panel of the Tracker screen (issue 5): cortical landmarks digitised with
// the pointer in two sets ("initial", then "later" in the operation), each through the accepted
// patient registration, and the brain shift between them per landmark and per axis (the seed's
// Table 3.3; docs/api/navigation.md "Cortical landmarks"). Logic in landmarks_model.ts.
import "./landmarks.css";
import { apiJson, plainMessage } from "./api";
import { h, table } from "./dom";
import {
  EARLIER, LATER, canReport, labelProblem, landmarkLines, shiftHeadline, shiftNotes, shiftTable, suggestLabel,
  type BrainShift, type Landmark, type LandmarksAnswer,
} from "./landmarks_model";

export interface LandmarksPanelDeps {
  alive: () => boolean;
  writable: boolean; // false for reviewers: the landmarks and the table shown, nothing recorded
  hasAccepted: () => boolean; // an accepted patient registration exists (the daemon refuses without)
}

export interface LandmarksPanel { el: HTMLElement; refresh: () => Promise<void> }

export function landmarksPanel(caseId: number, deps: LandmarksPanelDeps): LandmarksPanel {
  const base = `/api/cases/${caseId}/navigation`;
  let answer: LandmarksAnswer | null = null;
  let report: BrainShift | null = null;
  let set = EARLIER;
  let selected: string | null = null;
  let labelEdited = false;
  let busy = false;

  const setBtn = (name: string) => h("button", { class: "btn lm-set", type: "button", "data-testid": `lm-set-${name}`, "aria-pressed": "false" }, "");
  const setEarlier = setBtn(EARLIER), setLater = setBtn(LATER);
  const label = h("input", { class: "lm-label", type: "text", maxlength: "64", "aria-label": "Landmark label", "data-testid": "lm-label" });
  const record = h("button", { class: "btn primary lm-record", type: "button", "data-testid": "lm-record-btn" }, "Record landmark");
  const rename = h("button", { class: "btn", type: "button", "data-testid": "lm-rename-btn" }, "Rename");
  const remove = h("button", { class: "btn danger", type: "button", "data-testid": "lm-delete-btn" }, "Delete");
  const msg = h("p", { class: "nav-msg", role: "alert", "data-testid": "lm-msg", hidden: true });
  const list = h("div", { class: "lm-list", "data-testid": "lm-list" });
  const headline = h("p", { class: "lm-headline", "data-testid": "shift-headline" }, "");
  const tableBox = h("div", { class: "lm-table", "data-testid": "shift-box" });
  const notes = h("p", { class: "muted", "data-testid": "shift-notes" }, "");
  const readOnly = h("p", { class: "muted", hidden: deps.writable }, "Read-only: reviewers see the landmarks and the brain shift but cannot record.");
  const el = h("section", { class: "panel lm-panel", "data-testid": "landmarks-panel" },
    h("h2", {}, "Cortical landmarks"), readOnly,
    h("p", { class: "muted" }, "Touch a landmark on the cortex with the pointer, hold still, press Record. Re-digitise the same labels in the later set to see the brain shift."),
    h("div", { class: "nav-row" }, h("span", {}, "Set:"), setEarlier, setLater, label, record),
    msg,
    h("div", { class: "lm-cols" },
      h("div", {}, list, h("div", { class: "nav-row" }, rename, remove)),
      h("div", {}, headline, tableBox, notes)));

  const say = (text: string, bad = true) => {
    msg.textContent = text;
    msg.className = `nav-msg ${bad ? "bad" : "ok"}`;
    msg.hidden = !text;
  };
  const lms = (): Landmark[] => answer?.landmarks ?? [];

  function draw(): void {
    const count = (s: string) => lms().filter((l) => l.set === s).length;
    for (const [b, name] of [[setEarlier, EARLIER], [setLater, LATER]] as const) {
      b.textContent = `${name === EARLIER ? "Initial" : "Later"} (${count(name)})`;
      b.setAttribute("aria-pressed", String(set === name));
      b.classList.toggle("active", set === name);
      b.disabled = busy;
    }
    if (!labelEdited) label.value = suggestLabel(lms(), set);
    const accepted = deps.hasAccepted();
    record.disabled = !deps.writable || busy || !accepted || !!labelProblem(label.value);
    record.textContent = accepted ? `Record “${label.value}” (${set})` : "Record landmark (accept a registration first)";
    label.disabled = !deps.writable;
    const lines = landmarkLines(lms());
    list.replaceChildren(...lines.map((l) =>
      h("button", {
        class: `lm-row${l.label === selected ? " selected" : ""}`, type: "button", "data-testid": `lm-row-${l.label}`,
        "data-initial": l.earlier ? "true" : "false", "data-later": l.later ? "true" : "false",
        click: () => { selected = selected === l.label ? null : l.label; draw(); },
      },
      h("span", { class: "lm-row-label" }, l.label),
      h("span", { class: l.earlier ? "lm-in" : "lm-out" }, l.earlier ? "initial ✓" : "initial —"),
      h("span", { class: l.later ? "lm-in" : "lm-out" }, l.later ? "later ✓" : "later —"))));
    if (!lines.length) list.append(h("p", { class: "muted" }, "No landmarks recorded yet."));
    const sel = selected && lines.find((l) => l.label === selected);
    const inSet = sel && (set === EARLIER ? sel.earlier : sel.later);
    rename.hidden = remove.hidden = !deps.writable;
    rename.disabled = busy || !sel || !label.value || label.value === selected || !!labelProblem(label.value);
    rename.textContent = sel ? `Rename “${selected}” to “${label.value}”` : "Rename (select a landmark)";
    remove.disabled = busy || !inSet;
    remove.textContent = sel ? `Delete “${selected}” from ${set}` : "Delete (select a landmark)";
    if (report) {
      const t = shiftTable(report);
      const tab = table(t.head, t.rows, "shift-table");
      tab.classList.add("lm-shift");
      tab.append(h("tfoot", {}, h("tr", { "data-testid": "shift-summary" }, ...t.summary.map((c) => h("td", {}, c)))));
      tableBox.replaceChildren(tab);
      headline.textContent = shiftHeadline(report);
      headline.dataset.n = String(report.n);
      notes.textContent = shiftNotes(report);
    } else {
      tableBox.replaceChildren();
      headline.textContent = canReport(lms()) ? "" : "Record landmarks in both sets (same labels) to see the brain shift.";
      delete headline.dataset.n;
      notes.textContent = "";
    }
  }

  async function refresh(): Promise<void> {
    answer = await apiJson<LandmarksAnswer>("GET", `${base}/landmarks`);
    report = null;
    if (canReport(lms())) {
      try {
        report = await apiJson<BrainShift>("POST", `${base}/brain-shift`, { earlier: EARLIER, later: LATER });
      } catch (e) {
        say(plainMessage(e));
      }
    }
    if (deps.alive()) draw();
  }

  const act = async (what: () => Promise<void>) => {
    if (busy) return;
    busy = true;
    draw();
    try {
      await what();
    } catch (e) {
      say(plainMessage(e));
    } finally {
      busy = false;
      if (deps.alive()) draw();
    }
  };

  const chooseSet = (name: string) => { set = name; labelEdited = false; draw(); };
  setEarlier.addEventListener("click", () => chooseSet(EARLIER));
  setLater.addEventListener("click", () => chooseSet(LATER));
  label.addEventListener("input", () => { labelEdited = label.value !== ""; draw(); });
  record.addEventListener("click", () => act(async () => {
    const l = label.value.trim();
    const bad = labelProblem(l);
    if (bad) { say(bad); return; }
    const r = await apiJson<{ recorded: Landmark }>("POST", `${base}/landmarks/record`, { label: l, set });
    const p = r.recorded.p_image_mm.map((v) => v.toFixed(1)).join(", ");
    say(`Recorded “${l}” in ${set} at (${p}) mm (${r.recorded.frames} frames, still within ${r.recorded.spread_mm.toFixed(2)} mm).`, false);
    labelEdited = false;
    await refresh();
  }));
  rename.addEventListener("click", () => act(async () => {
    if (!selected) return;
    const to = label.value.trim();
    await apiJson("POST", `${base}/landmarks/rename`, { label: selected, new_label: to });
    say(`Renamed “${selected}” to “${to}”.`, false);
    selected = to;
    labelEdited = false;
    await refresh();
  }));
  remove.addEventListener("click", () => act(async () => {
    if (!selected) return;
    await apiJson("POST", `${base}/landmarks/delete`, { set, label: selected });
    say(`Deleted “${selected}” from ${set}.`, false);
    selected = null;
    await refresh();
  }));
  draw();
  return { el, refresh };
}
