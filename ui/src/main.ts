// CortexFuse kiosk UI, first cut: status bar, cases, case view with a rendered volume, jobs.
import "./style.css";
import { apiJson, apiRender, plainMessage, type RenderedImage } from "./api";
import { PushChannel, type PushState } from "./push";
import { fitFocalPx, RenderScheduler, renderSizes } from "./render_scheduler";
import { drawNmiPlot, type NmiPoint } from "./nmiplot";

// ---- tiny DOM helper ---------------------------------------------------------------------
type Attrs = Record<string, string | number | boolean | ((ev: Event) => void)>;
function h<K extends keyof HTMLElementTagNameMap>(tag: K, attrs: Attrs = {}, ...kids: (Node | string)[]): HTMLElementTagNameMap[K] {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (typeof v === "function") el.addEventListener(k.slice(2), v);
    else if (typeof v === "boolean") { if (v) el.setAttribute(k, ""); }
    else el.setAttribute(k, String(v));
  }
  for (const c of kids) el.append(c);
  return el;
}

// ---- shared state ------------------------------------------------------------------------
interface CaseSummary { id: number; uid: string; title: string; state: string; created_utc: string; updated_utc: string }
interface Job {
  id: number; kind: string; state: string; stage: string; fraction: number; message?: string;
  figures?: { evaluation?: number; nmi?: number; best_nmi?: number }; params?: Record<string, unknown>;
  error?: string; result?: Record<string, unknown>; cancel_requested?: boolean;
}
const jobs = new Map<number, Job>();
const nmiSeries = new Map<number, NmiPoint[]>();
let jobsListener: (() => void) | null = null;

const app = document.getElementById("app")!;
const statusBar = h("header", { class: "statusbar", "data-testid": "statusbar" });
const banners = h("div", { class: "banners", "aria-live": "polite" });
const nav = h("nav", { class: "tabs" });
const main = h("main", { class: "screen" });
app.append(statusBar, banners, nav, main);

// ---- error banners -----------------------------------------------------------------------
function showError(e: unknown): void {
  const text = plainMessage(e);
  for (const b of banners.querySelectorAll(".banner .text")) if (b.textContent === text) return; // once
  const banner = h("div", { class: "banner", role: "alert", "data-testid": "error-banner" },
    h("span", { class: "text" }, text),
    h("button", { class: "btn small", onclick: () => banner.remove() }, "Dismiss"));
  banners.append(banner);
}

// ---- status bar --------------------------------------------------------------------------
const sb = {
  tracker: h("span", { class: "pill", "data-testid": "sb-tracker" }, "Tracker: …"),
  tools: h("span", { class: "pill", "data-testid": "sb-tools" }, "Tools: …"),
  renderer: h("span", { class: "pill", "data-testid": "sb-renderer" }, "Renderer: …"),
  jobs: h("span", { class: "pill", "data-testid": "sb-jobs" }, "Jobs: …"),
  link: h("span", { class: "pill", "data-testid": "sb-link" }, "Link: …"),
};
statusBar.append(h("span", { class: "brand" }, "CortexFuse"), ...Object.values(sb));

function setPill(el: HTMLElement, text: string, level: "ok" | "warn" | "bad"): void {
  el.textContent = text;
  el.className = `pill ${level}`;
}

interface StatusSummary {
  tracker?: { state?: string; frame_rate_hz?: number };
  renderer?: { state?: string; backend?: string };
  jobs?: Record<string, { queued?: number; running?: number | null }> | { kinds?: Record<string, { queued?: number; running?: number | null }> };
}
function applyStatus(s: StatusSummary): void {
  const t = s.tracker ?? {};
  const hz = typeof t.frame_rate_hz === "number" ? ` ${t.frame_rate_hz.toFixed(0)} Hz` : "";
  setPill(sb.tracker, `Tracker: ${t.state ?? "unknown"}${hz}`, t.state === "streaming" ? "ok" : t.state ? "warn" : "bad");
  const r = s.renderer ?? {};
  setPill(sb.renderer, `Renderer: ${r.backend ?? "?"} (${r.state ?? "unknown"})`, r.state === "ready" ? "ok" : r.state === "failed" ? "bad" : "warn");
  const raw = s.jobs ?? {};
  const kinds = ("kinds" in raw && raw.kinds ? raw.kinds : raw) as Record<string, { queued?: number; running?: number | null }>;
  let running = 0, queued = 0;
  for (const k of Object.values(kinds)) {
    if (k && typeof k === "object") { if (k.running !== null && k.running !== undefined) running++; queued += k.queued ?? 0; }
  }
  setPill(sb.jobs, `Jobs: ${running} running, ${queued} queued`, "ok");
}

interface TrackerFrame { seq: number; tools?: { name: string; status: string }[] }
function applyFrame(f: TrackerFrame): void {
  const tools = f.tools ?? [];
  const seen = tools.filter((t) => t.status === "ok").map((t) => t.name);
  const missing = tools.filter((t) => t.status !== "ok").map((t) => t.name);
  setPill(sb.tools, `Tools: ${seen.join(", ") || "none"} seen${missing.length ? `; ${missing.join(", ")} missing` : ""}`,
    missing.length ? "warn" : "ok");
  sb.tools.dataset.seq = String(f.seq);
}

async function pollStatus(): Promise<void> {
  try {
    const s = await apiJson<{ modules: Record<string, unknown> }>("GET", "/api/status");
    const m = s.modules as StatusSummary & Record<string, unknown>;
    applyStatus({ tracker: m.tracker as StatusSummary["tracker"], renderer: m.renderer as StatusSummary["renderer"], jobs: m.jobs as StatusSummary["jobs"] });
  } catch (e) {
    setPill(sb.tracker, "Tracker: unknown", "bad");
    showError(e);
  }
}

function onPushState(s: PushState): void {
  setPill(sb.link, s === "open" ? "Live" : s === "connecting" ? "Connecting…" : "Daemon unreachable", s === "open" ? "ok" : s === "connecting" ? "warn" : "bad");
  if (s === "open") { pollStatus(); loadJobs(); }
}

function onNotify(method: string, params: unknown): void {
  if (method === "notify_status") applyStatus(params as StatusSummary);
  else if (method === "notify_tracker_frame") applyFrame(params as TrackerFrame);
  else if (method === "notify_job") upsertJob(params as Job);
}

const wsUrl = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/ws`;
new PushChannel(wsUrl, onNotify, onPushState).start();

// ---- jobs store --------------------------------------------------------------------------
function upsertJob(j: Job): void {
  if (typeof j?.id !== "number") return;
  jobs.set(j.id, j);
  const ev = j.figures?.evaluation, nmi = j.figures?.nmi;
  if (typeof ev === "number" && typeof nmi === "number") {
    const s = nmiSeries.get(j.id) ?? [];
    if (!s.length || s[s.length - 1].evaluation < ev) s.push({ evaluation: ev, nmi });
    nmiSeries.set(j.id, s);
  }
  jobsListener?.();
}
async function loadJobs(): Promise<void> {
  try {
    const r = await apiJson<{ jobs: Job[] }>("GET", "/api/jobs");
    for (const j of r.jobs) upsertJob(j);
  } catch (e) { showError(e); }
}

// The push channel drops its oldest messages when the daemon is overloaded (docs/api/push.md),
// so a job's last notify_job can be lost: while any job is queued or running, read the list
// every 2 s as well.
setInterval(() => {
  if ([...jobs.values()].some((j) => j.state === "queued" || j.state === "running")) loadJobs();
}, 2000);

// ---- router ------------------------------------------------------------------------------
const tabs: [string, string][] = [["#/cases", "Cases"], ["#/jobs", "Jobs"]];
let leaveScreen: (() => void) | null = null;
function route(): void {
  leaveScreen?.();
  leaveScreen = null;
  jobsListener = null;
  main.replaceChildren();
  const hash = location.hash || "#/cases";
  nav.replaceChildren(...tabs.map(([href, label]) =>
    h("a", { href, class: `tab${hash.startsWith(href) || (href === "#/cases" && hash.startsWith("#/case/")) ? " active" : ""}` }, label)));
  const m = /^#\/case\/(\d+)$/.exec(hash);
  if (m) caseScreen(Number(m[1]));
  else if (hash.startsWith("#/jobs")) jobsScreen();
  else casesScreen();
}
window.addEventListener("hashchange", route);

// ---- Cases -------------------------------------------------------------------------------
function fmtTime(utc: string): string {
  return utc ? utc.replace("T", " ").replace(/\.\d+Z$|Z$/, "") + " UTC" : "";
}
function casesScreen(): void {
  const search = h("input", { type: "search", placeholder: "Search title, MRN, patient", class: "field grow", "data-testid": "case-search" });
  const list = h("div", { class: "list", "data-testid": "case-list" });
  const title = h("input", { type: "text", placeholder: "New case title", class: "field grow", "data-testid": "new-case-title" });
  let timer: number | undefined;
  const load = async () => {
    try {
      const q = search.value.trim();
      const r = await apiJson<{ cases: CaseSummary[] }>("GET", `/api/cases?limit=200${q ? `&text=${encodeURIComponent(q)}` : ""}`);
      list.replaceChildren(...(r.cases.length ? r.cases.map((c) =>
        h("a", { class: "row", href: `#/case/${c.id}`, "data-testid": "case-row" },
          h("span", { class: "row-title" }, c.title || "(untitled)"),
          h("span", { class: "badge" }, c.state.replace(/_/g, " ")),
          h("span", { class: "muted" }, fmtTime(c.updated_utc)))) :
        [h("p", { class: "muted" }, q ? "No case matches this search." : "No cases yet. Create one below.")]));
    } catch (e) { showError(e); }
  };
  search.addEventListener("input", () => { clearTimeout(timer); timer = window.setTimeout(load, 250); });
  const create = async (ev: Event) => {
    ev.preventDefault();
    const t = title.value.trim();
    if (!t) { showError(new Error("Type a title for the new case first.")); return; }
    try {
      const c = await apiJson<CaseSummary>("POST", "/api/cases", { title: t });
      title.value = "";
      location.hash = `#/case/${c.id}`;
    } catch (e) { showError(e); }
  };
  main.append(
    h("h1", {}, "Cases"),
    h("div", { class: "toolbar" }, search),
    list,
    h("form", { class: "toolbar", onsubmit: create }, title, h("button", { class: "btn primary", type: "submit", "data-testid": "create-case" }, "Create case")),
  );
  load();
}

// ---- Case view ---------------------------------------------------------------------------
// View changes and pictures shown, with their time: the e2e test reads it to measure how soon
// a touch shows a new picture (window.cfRenderTimeline).
const timeline: { what: string; t: number; size: string }[] = [];
(window as unknown as { cfRenderTimeline: typeof timeline }).cfRenderTimeline = timeline;
interface View { preset: string; opacity: number; view: string }
const ORBIT = ["left", "anterior", "right", "posterior"];

function caseScreen(id: number): void {
  const header = h("div", { class: "toolbar" }, h("a", { class: "btn", href: "#/cases" }, "‹ Cases"), h("h1", { class: "grow" }, `Case ${id}`));
  const img = h("img", { class: "render", alt: "Rendered view of the volume", "data-testid": "render-image", draggable: "false" });
  const stage = h("div", { class: "render-stage", "data-testid": "render-stage" }, img);
  const info = h("div", { class: "muted", "data-testid": "render-info" }, "Rendering…");
  const presets = h("div", { class: "choices", "data-testid": "presets" });
  const views = h("div", { class: "choices two" });
  const opacityOut = h("span", { class: "value" }, "100 %");
  const opacity = h("input", { type: "range", min: 0, max: 100, step: 5, value: 100, class: "slider", "data-testid": "opacity" });
  const side = h("aside", { class: "controls" },
    h("h2", {}, "Preset"), presets,
    h("h2", {}, "Opacity ", opacityOut), opacity,
    h("h2", {}, "View"), views,
    h("p", { class: "muted" }, "Drag on the picture to turn the head."), info);
  main.append(header, h("div", { class: "case-layout" }, stage, side));

  const v: View = { preset: "cortex_t1", opacity: 1, view: "left" };
  let url = "";
  let alive = true;
  const sched = new RenderScheduler<View>({
    render: (view, size) => apiRender({ width: size.width, height: size.height, preset: view.preset, opacity: view.opacity, view: view.view,
                                       distance_mm: 450, focal_px: fitFocalPx(size.width, size.height, 450, 95) }),
    onImage: (r, _view, size, full) => {
      if (!alive) return;
      const ri = r as RenderedImage;
      if (url) URL.revokeObjectURL(url);
      url = URL.createObjectURL(ri.blob);
      img.src = url;
      img.dataset.size = `${size.width}x${size.height}`;
      img.dataset.full = String(full);
      info.textContent = `${ri.width}x${ri.height} ${full ? "" : "preview "}in ${ri.renderMs.toFixed(0)} ms (${ri.renderer})`;
      timeline.push({ what: full ? "full" : "preview", t: performance.now(), size: `${size.width}x${size.height}` });
    },
    onError: (e) => alive && showError(e),
    sizes: () => renderSizes(stage.clientWidth || 640, stage.clientHeight || 480, 1, { width: 1280, height: 1024 }),
  });
  leaveScreen = () => { alive = false; if (url) URL.revokeObjectURL(url); };

  const mark = (box: HTMLElement, val: string) => box.querySelectorAll("button").forEach((b) => b.classList.toggle("active", b.dataset.value === val));
  const setView = (name: string) => { v.view = name; mark(views, name); };
  for (const name of ["left", "right", "anterior", "posterior", "superior", "inferior"])
    views.append(h("button", { class: "btn", "data-value": name, onclick: () => { setView(name); sched.now({ ...v }); } }, name));
  setView(v.view);
  opacity.addEventListener("input", () => { v.opacity = Number(opacity.value) / 100; opacityOut.textContent = `${opacity.value} %`; sched.interactive({ ...v }); });

  apiJson<{ presets: string[] }>("GET", "/api/render/presets").then((r) => {
    presets.replaceChildren(...r.presets.map((p) => h("button", { class: "btn", "data-value": p, onclick: () => { v.preset = p; mark(presets, p); sched.now({ ...v }); } }, p.replace(/_/g, " "))));
    mark(presets, v.preset);
  }, showError);
  const layout = main.querySelector(".case-layout")!;
  apiJson<CaseSummary & { patient?: unknown }>("GET", `/api/cases/${id}`).then((c) => {
    if (!alive) return;
    header.querySelector("h1")!.textContent = c.title || `Case ${id}`;
    header.append(h("span", { class: "badge", "data-testid": "case-state" }, c.state.replace(/_/g, " ")));
    sched.now({ ...v });
  }, (e) => {
    if (!alive) return;
    showError(e);
    layout.replaceChildren(h("p", { class: "muted", "data-testid": "case-missing" },
      "This case could not be opened. Go back to the cases and pick another, or create one."));
  });

  // Drag: every 60 px sideways steps round the head, up/down looks from above/below.
  let start: { x: number; y: number; view: string } | null = null;
  stage.addEventListener("pointerdown", (e) => { start = { x: e.clientX, y: e.clientY, view: v.view }; stage.setPointerCapture(e.pointerId); });
  stage.addEventListener("pointermove", (e) => {
    if (!start) return;
    const dx = e.clientX - start.x, dy = e.clientY - start.y;
    let next = start.view;
    if (Math.abs(dy) > 80 && Math.abs(dy) > Math.abs(dx)) next = dy < 0 ? "inferior" : "superior";
    else {
      const i0 = Math.max(0, ORBIT.indexOf(start.view));
      const steps = Math.round(dx / 60);
      next = ORBIT[(((i0 + steps) % 4) + 4) % 4];
    }
    if (next !== v.view) { setView(next); timeline.push({ what: "change", t: performance.now(), size: "" }); sched.interactive({ ...v }); }
  });
  const end = () => { start = null; };
  stage.addEventListener("pointerup", end);
  stage.addEventListener("pointercancel", end);
}

// ---- Jobs --------------------------------------------------------------------------------
function jobsScreen(): void {
  const folder = h("select", { class: "field grow", "data-testid": "case-folder" });
  const startBtn = h("button", { class: "btn primary", "data-testid": "start-register" }, "Start registration");
  const list = h("div", { class: "list", "data-testid": "job-list" });
  const canvas = h("canvas", { class: "plot", width: 480, height: 200, "data-testid": "nmi-plot" });
  const plotTitle = h("h2", {}, "NMI against evaluations");
  let selected: number | null = null;
  main.append(h("h1", {}, "Jobs"),
    h("div", { class: "toolbar" }, h("label", { class: "muted" }, "Phantom case"), folder, startBtn),
    h("div", { class: "jobs-layout" }, list, h("div", { class: "plot-box" }, plotTitle, canvas)));

  apiJson<{ folders: string[] }>("GET", "/api/case-folders").then((r) => {
    folder.replaceChildren(...r.folders.map((f) => h("option", { value: f }, f)));
    if (!r.folders.length) folder.append(h("option", { value: "" }, "No case folders yet"));
  }, showError);

  startBtn.addEventListener("click", async () => {
    if (!folder.value) { showError(new Error("No phantom case folder to register yet; the daemon makes one at start.")); return; }
    try {
      const j = await apiJson<Job>("POST", "/api/jobs", { kind: "register", params: { case: folder.value } });
      selected = j.id;
      upsertJob(j);
    } catch (e) { showError(e); }
  });

  // Cards are made once per job and updated in place: progress arrives up to 10 times a second
  // and a button re-created under a finger would swallow the touch.
  interface Card { el: HTMLElement; badge: HTMLElement; bar: HTMLElement; stage: HTMLElement; nmi: HTMLElement;
                   evals: HTMLElement; error: HTMLElement; cancel: HTMLButtonElement }
  const cards = new Map<number, Card>();
  const empty = h("p", { class: "muted" }, "No jobs yet.");
  const makeCard = (j: Job): Card => {
    const c: Card = {
      el: h("div", { class: "job", "data-testid": "job-card", onclick: () => { selected = j.id; render(); } }),
      badge: h("span", { class: "badge" }), bar: h("div", { class: "bar" }), stage: h("span"), nmi: h("span"),
      evals: h("span"), error: h("div", { class: "job-error" }),
      cancel: h("button", { class: "btn danger", "data-testid": "cancel-job" }, "Cancel"),
    };
    c.cancel.addEventListener("click", async (ev) => {
      ev.stopPropagation();
      c.cancel.disabled = true;
      try { upsertJob(await apiJson<Job>("POST", `/api/jobs/${j.id}/cancel`)); } catch (e) { c.cancel.disabled = false; showError(e); }
    });
    c.el.append(
      h("div", { class: "job-head" }, h("strong", {}, `#${j.id} ${j.kind}`), c.badge,
        h("span", { class: "muted grow" }, String(j.params?.case ?? j.params?.case_id ?? ""))),
      h("div", { class: "progress" }, c.bar), h("div", { class: "job-figs" }, c.stage, c.nmi, c.evals), c.error, c.cancel);
    return c;
  };
  const render = () => {
    const all = [...jobs.values()].sort((a, b) => b.id - a.id);
    if (selected === null && all.length) selected = all[0].id;
    const order: HTMLElement[] = [];
    for (const j of all) {
      let c = cards.get(j.id);
      if (!c) { c = makeCard(j); cards.set(j.id, c); }
      const active = j.state === "queued" || j.state === "running";
      const nmi = j.figures?.nmi, best = j.figures?.best_nmi;
      const pct = Math.round((j.fraction ?? 0) * 100);
      c.el.className = `job${j.id === selected ? " selected" : ""}`;
      c.el.dataset.state = j.state;
      c.badge.className = `badge ${j.state}`;
      c.badge.textContent = j.state;
      c.bar.style.width = `${pct}%`;
      c.stage.textContent = `${j.stage}${active ? ` · ${pct} %` : ""}`;
      c.nmi.textContent = typeof nmi === "number" ? `NMI ${nmi.toFixed(4)} (best ${best?.toFixed(4) ?? "–"})` : "";
      c.evals.textContent = typeof j.figures?.evaluation === "number" ? `${j.figures.evaluation} evaluations` : "";
      c.error.textContent = j.error ?? "";
      c.error.hidden = !j.error;
      c.cancel.hidden = !active;
      if (j.cancel_requested) { c.cancel.disabled = true; c.cancel.textContent = "Cancelling…"; }
      order.push(c.el);
    }
    if (!order.length) order.push(empty);
    if (order.length !== list.children.length || order.some((el, i) => list.children[i] !== el)) list.replaceChildren(...order);
    const ctx = canvas.getContext("2d");
    if (ctx) drawNmiPlot(ctx, selected !== null ? nmiSeries.get(selected) ?? [] : [], canvas.width, canvas.height);
    plotTitle.textContent = selected !== null ? `NMI against evaluations, job #${selected}` : "NMI against evaluations";
  };
  jobsListener = render;
  render();
  loadJobs();
}

pollStatus();
route();
