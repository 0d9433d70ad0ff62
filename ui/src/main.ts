// CortexFuse kiosk UI: status bar, login (remote review), cases, case view with a rendered
// volume, the case's contents and audit trail, jobs.
import "./style.css";
import { ApiError, UserMessage, apiBlob, apiJson, apiPostBlob, apiRender, apiUpload, auth, plainMessage, type RenderedImage } from "./api";
import { cardinalPath, clampPx, defaultCamera, imageKind, insertRoiPoint, nearest, projectPoint, type Px } from "./photo_marks";
import { mediaChoices, mediaImport, mediaLine, type MediaAnswer } from "./media";
import { ThumbnailLoader, thumbCaption } from "./thumbnails";
import { AlignmentFetcher, alignmentHeadline, highErrorPx, pairErrorText } from "./initial_alignment";
import { PushChannel, type PushState } from "./push";
import { fitFocalPx, RenderScheduler, renderSizes } from "./render_scheduler";
import { drawNmiPlot, type NmiPoint } from "./nmiplot";
import { h, table } from "./dom";
import { LinkMonitor, restartNote, TrackerMonitor } from "./link";
import { dragOrbit, NAMED_VIEWS, namedViewOf, orbitPose, zoomOrbit, type Orbit, type Vec3 } from "./orbit";
import { TfEditor } from "./tf_editor";
import { centreLps, type Volume as NiftiVolume } from "./nifti";
import { parseNiftiOffThread } from "./off_thread";
import { orbitCamera, pinchPan } from "./fused_pose";
import { mountTags, type Intrinsics } from "./tags";
import { mountLiveView } from "./live_view";
import { planScreen, type PlanJob } from "./plan_screen";
import type { TfJson } from "./tf_model";
import { canWrite, KIOSK, loadSession, roleLabel, saveSession, sessionFromLogin, wsUrl, type Session } from "./session";
import { auditRows, fmtBytes, fmtTime, holdings, patientLine, registrationRows, type AuditEntry, type CaseRecord } from "./case_detail";
import { trackerScreen } from "./tracker_screen";
import { FusedModalityPanel, fusedLayers, fusedRequest, layersNeedGl } from "./fused_modalities";
import { caseRenderFields, defaultLayers, histogramBars, histogramPath, layerHistogramPath, MODALITY_LABEL, ModalityTabs, newestT1, planModalities, type ModalityLayer, type VolumeHistogram } from "./case_render";
import { renderFailureNextStep, volumeRefusalNextStep } from "./next_step";
import { LeaveGuard, unsavedMarksText } from "./leave_guard";
import { DaemonDraftSync, draftRequester, loadDaemonDraft, MarksDrafts, pickDraft, restoredText, saveFailedText, toDaemonBody, withoutSavedParts } from "./marks_draft";
import { jobsPill, rendererPill, toolsPill, trackerPill } from "./status_pills";

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
const jobSubscribers = new Set<(j: Job) => void>(); // screens that follow jobs (the Preoperative step)

const app = document.getElementById("app")!;
const statusBar = h("header", { class: "statusbar", "data-testid": "statusbar" });
const banners = h("div", { class: "banners", "aria-live": "polite" });
const nav = h("nav", { class: "tabs" });
const main = h("main", { class: "screen" });
// Passing notices sit in the tab row, right of the tabs (issue 7, 7.30): over no control of a
// screen (at 1280x800 the bottom right was the side panel's Save/Clear), not pushing the picture down.
const toasts = h("div", { class: "toasts", "aria-live": "polite", "data-testid": "notices" });
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

/** The text ending as a sentence (the daemon's one-line errors have no full stop). */
function sentence(t: string): string {
  return /[.!?…)]$/.test(t.trim()) ? t.trim() : `${t.trim()}.`;
}

/** How many passing notices are shown side by side at most, and for how long. */
const NOTICES_MAX = 2;
const NOTICE_LIFE_MS = 6000;

/** A passing notice (not an error): shown for NOTICE_LIFE_MS, or until dismissed; at most
 *  NOTICES_MAX (the oldest goes first). */
function showNotice(text: string): void {
  const banner = h("div", { class: "banner info", role: "status", "data-testid": "notice-banner" },
    h("span", { class: "text" }, text),
    h("button", { class: "btn small", onclick: () => banner.remove() }, "Dismiss"));
  toasts.append(banner);
  while (toasts.children.length > NOTICES_MAX) toasts.firstElementChild?.remove();
  setTimeout(() => banner.remove(), NOTICE_LIFE_MS);
}

// The live link: a standing line while it is lost (not dismissable: it goes when the link is back).
const linkBanner = h("div", { class: "banner warn", role: "alert", "data-testid": "link-banner", hidden: true }, h("span", { class: "text" }));
banners.prepend(linkBanner);
// The tracker: a standing line while it has stopped streaming (issue 7: a tracker that drops out).
const trackerBanner = h("div", { class: "banner warn", role: "alert", "data-testid": "tracker-banner", hidden: true }, h("span", { class: "text" }));
linkBanner.after(trackerBanner);
const trackerMonitor = new TrackerMonitor();
const linkMonitor = new LinkMonitor();
let daemonStartedUtc: string | null = null;
let lastSessionProbe = 0;

// ---- status bar --------------------------------------------------------------------------
const sb = {
  tracker: h("span", { class: "pill", "data-testid": "sb-tracker" }, "Tracker: …"),
  tools: h("span", { class: "pill", "data-testid": "sb-tools" }, "Tools: …"),
  renderer: h("span", { class: "pill", "data-testid": "sb-renderer" }, "Renderer: …"),
  jobs: h("span", { class: "pill", "data-testid": "sb-jobs" }, "Jobs: …"),
  link: h("span", { class: "pill", "data-testid": "sb-link" }, "Link: …"),
  role: h("span", { class: "pill", "data-testid": "sb-role" }, "…"),
};
const authBtn = h("button", { class: "btn small", "data-testid": "auth-button", hidden: true }, "Log in");
statusBar.append(h("span", { class: "brand" }, "CortexFuse"), ...Object.values(sb), authBtn);

// ---- session (kiosk or a logged-in user) --------------------------------------------------
// The kiosk (loopback, no token) may do everything; other hosts get 401 until they log in
// (docs/api/cases.md). needLogin: the daemon asked for a login; the login screen is shown.
let session: Session = KIOSK;
let needLogin = false;
let loginNote = "";
let loginFromKiosk = false; // the kiosk asked to log in as someone: "Back to the kiosk" is offered
let push: PushChannel | null = null;

function applySession(): void {
  auth.token = session.token;
  document.body.classList.toggle("read-only", !canWrite(session));
  setPill(sb.role, needLogin ? "Not logged in" : roleLabel(session), needLogin ? "warn" : session.role === "reviewer" ? "warn" : "ok");
  authBtn.hidden = needLogin;
  authBtn.textContent = session.token ? "Log out" : "Log in";
}

function startPush(): void {
  push?.stop();
  push = new PushChannel(wsUrl(location, session), onNotify, onPushState, showError);
  push.start();
}

function askLogin(note: string, fromKiosk = false): void {
  loginFromKiosk = fromKiosk;
  push?.stop();
  push = null;
  setPill(sb.link, "Link: after login", "warn");
  needLogin = true;
  loginNote = note;
  session = KIOSK;
  saveSession(sessionStorage, null);
  applySession();
  route();
}

// Any 401 (an expired session, or a host that must log in): the login screen, saying why.
auth.onUnauthorized = (e: ApiError) => {
  if (needLogin) return;
  askLogin(session.token ? "Your session has ended (expired, or logged out elsewhere). Log in again to go on." : "This screen is not the cart's kiosk: log in to continue.");
  void e;
};

authBtn.addEventListener("click", async () => {
  if (!session.token) { askLogin("Log in as another user (a reviewer sees the cases read-only).", true); return; }
  try { await apiJson("POST", "/api/logout"); } catch { /* the session ends here either way */ }
  saveSession(sessionStorage, null);
  session = KIOSK;
  auth.token = null;
  await probeAccess("You have logged out.");
});

/** Whether the daemon lets this browser in as it is (kiosk, or the stored session); else the
 *  login screen. */
async function probeAccess(note = ""): Promise<void> {
  try {
    await apiJson("GET", "/api/cases?limit=1");
  } catch (e) {
    if (e instanceof ApiError && e.status === 401) {
      if (!needLogin) askLogin(note ? `${note} This screen is not the cart's kiosk: log in to continue.` : "This screen is not the cart's kiosk: log in to continue.");
      return;
    }
    showError(e); // unreachable or failing: the screens say so, the push channel retries
  }
  needLogin = false;
  applySession();
  startPush();
  route();
}

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
  const tv = trackerMonitor.update(t.state, (t as { last_error?: string }).last_error ?? "");
  trackerBanner.hidden = tv.banner === null;
  trackerBanner.querySelector(".text")!.textContent = tv.banner ?? "";
  if (tv.notice) showNotice(tv.notice);
  setPill(sb.tracker, trackerPill(t.state, t.frame_rate_hz), t.state === "streaming" ? "ok" : t.state ? "warn" : "bad");
  const r = s.renderer ?? {};
  setPill(sb.renderer, rendererPill(r.state, r.backend), r.state === "ready" ? "ok" : r.state === "failed" ? "bad" : "warn");
  const raw = s.jobs ?? {};
  const kinds = ("kinds" in raw && raw.kinds ? raw.kinds : raw) as Record<string, { queued?: number; running?: number | null }>;
  let running = 0, queued = 0;
  for (const k of Object.values(kinds)) {
    if (k && typeof k === "object") { if (k.running !== null && k.running !== undefined) running++; queued += k.queued ?? 0; }
  }
  setPill(sb.jobs, jobsPill(running, queued), "ok");
}

interface TrackerFrame { seq: number; tools?: { name: string; status: string }[] }
function applyFrame(f: TrackerFrame): void {
  const tools = f.tools ?? [];
  const seen = tools.filter((t) => t.status === "ok").map((t) => t.name);
  const missing = tools.filter((t) => t.status !== "ok").map((t) => t.name);
  setPill(sb.tools, toolsPill(seen, missing),
    missing.length ? "warn" : "ok");
  sb.tools.dataset.seq = String(f.seq);
}

async function pollStatus(): Promise<void> {
  try {
    const s = await apiJson<{ modules: Record<string, unknown>; started_utc?: string }>("GET", "/api/status");
    const restarted = restartNote(daemonStartedUtc, s.started_utc);
    if (s.started_utc) daemonStartedUtc = s.started_utc;
    if (restarted) {
      showNotice(restarted);
      // The daemon keeps jobs in memory only: the old ones are gone with it.
      jobs.clear();
      nmiSeries.clear();
      loadJobs();
    }
    const m = s.modules as StatusSummary & Record<string, unknown>;
    applyStatus({ tracker: m.tracker as StatusSummary["tracker"], renderer: m.renderer as StatusSummary["renderer"], jobs: m.jobs as StatusSummary["jobs"] });
  } catch (e) {
    setPill(sb.tracker, trackerPill(undefined, undefined), "bad");
    showError(e);
  }
}

function onPushState(s: PushState): void {
  if (needLogin) return;
  setPill(sb.link, s === "open" ? "Live" : s === "connecting" ? "Connecting…" : "Daemon unreachable", s === "open" ? "ok" : s === "connecting" ? "warn" : "bad");
  // A refused upgrade looks like a lost link; with a token it may be an expired session: ask
  // over HTTP (a 401 there brings the login screen), at most every 5 s.
  if (s === "closed" && session.token && Date.now() - lastSessionProbe > 5000) {
    lastSessionProbe = Date.now();
    apiJson("GET", "/api/cases?limit=1").catch(() => { /* a 401 is handled by auth.onUnauthorized; unreachable is on the link line */ });
  }
  const lv = linkMonitor.update(s);
  linkBanner.hidden = lv.banner === null;
  linkBanner.querySelector(".text")!.textContent = lv.banner ?? "";
  if (lv.notice) showNotice(lv.notice);
  if (s === "open") { pollStatus(); loadJobs(); }
}

function onNotify(method: string, params: unknown): void {
  if (method === "notify_status") applyStatus(params as StatusSummary);
  else if (method === "notify_tracker_frame") applyFrame(params as TrackerFrame);
  else if (method === "notify_job") upsertJob(params as Job);
}


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
  for (const f of jobSubscribers) f(j);
}
async function loadJobs(): Promise<void> {
  if (needLogin) return;
  try {
    const r = await apiJson<{ jobs: Job[] }>("GET", "/api/jobs");
    for (const j of r.jobs) upsertJob(j);
  } catch (e) { showError(e); }
}

// The push channel drops its oldest messages when the daemon is overloaded (docs/api/push.md),
// so a job's last notify_job can be lost: while any job is queued or running, read the list
// every 2 s as well.
setInterval(() => {
  if (!needLogin && [...jobs.values()].some((j) => j.state === "queued" || j.state === "running")) loadJobs();
}, 2000);

// ---- router ------------------------------------------------------------------------------
const tabs: [string, string][] = [["#/cases", "Cases"], ["#/jobs", "Jobs"]];
let leaveScreen: (() => void) | null = null;
const leaveGuard = new LeaveGuard();
const marksDrafts = new MarksDrafts(sessionStorage);
const draftRequest = draftRequester(() => auth.token); // the daemon's copy of unsaved marks (7.47)
const leaveAsk = h("div", { class: "banner warn", role: "alert", "data-testid": "leave-ask", hidden: true });
banners.append(leaveAsk);

/** A hash change: routed, unless the shown screen has unsaved edits; then the hash is put back
 *  and the person is asked (7.47). */
function onHashChange(): void {
  const d = leaveGuard.decide(location.hash || "#/cases");
  if (d.kind === "go") { route(); return; }
  history.replaceState(null, "", d.back);
  leaveAsk.replaceChildren(h("span", { class: "text" }, d.reason),
    h("button", { class: "btn small", "data-testid": "leave-stay", onclick: () => { leaveAsk.hidden = true; } }, "Stay"),
    h("button", { class: "btn small", "data-testid": "leave-anyway", onclick: () => { leaveAsk.hidden = true; leaveGuard.allowOnce(d.to); location.hash = d.to; } }, "Leave without saving"));
  leaveAsk.hidden = false;
}

function route(): void {
  leaveGuard.arrived(location.hash || "#/cases");
  leaveAsk.hidden = true;
  leaveScreen?.();
  leaveScreen = null;
  jobsListener = null;
  main.replaceChildren();
  if (needLogin) { nav.replaceChildren(toasts); loginScreen(); return; }
  const hash = location.hash || "#/cases";
  nav.replaceChildren(...tabs.map(([href, label]) =>
    h("a", { href, class: `tab${hash.startsWith(href) || (href === "#/cases" && hash.startsWith("#/case/")) ? " active" : ""}` }, label)), toasts);
  const m = /^#\/case\/(\d+)(?:\/([a-z]+))?$/.exec(hash);
  if (m) caseScreen(Number(m[1]), m[2] ?? "view");
  else if (hash.startsWith("#/jobs")) jobsScreen();
  else casesScreen();
}
window.addEventListener("hashchange", onHashChange);

// ---- Login -------------------------------------------------------------------------------
function loginScreen(): void {
  const name = h("input", { type: "text", class: "field", autocomplete: "username", placeholder: "User name", "data-testid": "login-name" });
  const password = h("input", { type: "password", class: "field", autocomplete: "current-password", placeholder: "Password", "data-testid": "login-password" });
  const msg = h("p", { class: "login-error", role: "alert", "data-testid": "login-error", hidden: true });
  const submit = h("button", { class: "btn primary", type: "submit", "data-testid": "login-submit" }, "Log in");
  const cancel = h("button", { class: "btn", type: "button", "data-testid": "login-cancel", hidden: !loginFromKiosk }, "Back to the kiosk");
  const login = async (ev: Event) => {
    ev.preventDefault();
    msg.hidden = true;
    if (!name.value.trim() || !password.value) { msg.textContent = "Type your user name and password."; msg.hidden = false; return; }
    submit.disabled = true;
    try {
      auth.token = null;
      const s = sessionFromLogin(await apiJson("POST", "/api/login", { name: name.value.trim(), password: password.value }));
      session = s;
      saveSession(sessionStorage, s);
      needLogin = false;
      loginNote = "";
      applySession();
      startPush();
      if (!location.hash || location.hash === "#/login") location.hash = "#/cases";
      route();
    } catch (e) {
      msg.textContent = e instanceof ApiError && e.status === 401
        ? "Wrong user name or password. Check both and try again; an administrator can reset the password."
        : plainMessage(e);
      msg.hidden = false;
      password.value = "";
      password.focus();
    } finally { submit.disabled = false; }
  };
  // "Back to the kiosk": only on the cart (loopback answers without a login).
  cancel.addEventListener("click", () => { needLogin = false; probeAccess(); });
  main.append(h("form", { class: "login", onsubmit: login, "data-testid": "login-form" },
    h("h1", {}, "Log in"),
    h("p", { class: "muted", "data-testid": "login-note" }, loginNote || "Log in with your CortexFuse user."),
    h("label", {}, "User name"), name, h("label", {}, "Password"), password, msg,
    h("div", { class: "toolbar" }, submit, cancel)));
  name.focus();
}

// ---- Cases -------------------------------------------------------------------------------
// The archive's thumbnails (src/thumbnails.ts): kept for the tab per case and its last change.
const thumbs = new ThumbnailLoader();
/** A row's thumbnail: the picture (fused view or photo) or a placeholder saying there is none. */
function caseThumb(c: CaseSummary): HTMLElement {
  const box = h("span", { class: "thumb", "data-testid": "case-thumb", "data-source": "loading" }, h("span", { class: "thumb-text" }, "…"));
  thumbs.get(c.id, c.updated_utc).then((t) => {
    box.dataset.source = t.source;
    const caption = thumbCaption(t);
    box.title = t.note ? `${caption}: ${t.note}` : caption;
    box.replaceChildren(t.url ? h("img", { src: t.url, alt: `${caption} of ${c.title || "the case"}`, draggable: "false" }) : h("span", { class: "thumb-text" }, caption));
  });
  return box;
}

function casesScreen(): void {
  const search = h("input", { type: "search", placeholder: "Search title, MRN, patient", class: "field grow", "data-testid": "case-search" });
  const list = h("div", { class: "list", "data-testid": "case-list" });
  const title = h("input", { type: "text", placeholder: "New case title", class: "field grow", "data-testid": "new-case-title" });
  let timer: number | undefined;
  const load = async () => {
    try {
      const q = search.value.trim();
      const r = await apiJson<{ cases: CaseSummary[] }>("GET", `/api/cases?limit=200&sort=${encodeURIComponent(sort.value)}${q ? `&text=${encodeURIComponent(q)}` : ""}`);
      list.replaceChildren(...(r.cases.length ? r.cases.map((c) =>
        h("a", { class: "row", href: `#/case/${c.id}`, "data-testid": "case-row" },
          caseThumb(c),
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
    if (!t) { showError(new UserMessage("Type a title for the new case first.")); return; }
    try {
      const c = await apiJson<CaseSummary>("POST", "/api/cases", { title: t });
      title.value = "";
      location.hash = `#/case/${c.id}`;
    } catch (e) { showError(e); }
  };
  // Sorting (the API's sort keys); kept for this tab.
  const sort = h("select", { class: "field", "data-testid": "case-sort", "aria-label": "Sort the cases" },
    ...[["updated_desc", "Last changed first"], ["updated_asc", "Last changed last"], ["created_desc", "Newest first"], ["created_asc", "Oldest first"],
        ["title_asc", "Title A–Z"], ["title_desc", "Title Z–A"]].map(([v, l]) => h("option", { value: v }, l)));
  sort.value = sessionStorage.getItem("cortexfuse.sort") ?? "updated_desc";
  sort.addEventListener("change", () => { sessionStorage.setItem("cortexfuse.sort", sort.value); load(); });
  main.append(h("h1", {}, "Cases"), h("div", { class: "toolbar" }, search, sort), list);
  if (canWrite(session)) {
    // Import a case folder (the phantom generator's, under the state folder's cases/) into the store.
    const folder = h("select", { class: "field grow", "data-testid": "import-folder" });
    const importBtn = h("button", { class: "btn", type: "button", "data-testid": "import-case" }, "Import case folder");
    importBtn.addEventListener("click", async () => {
      if (!folder.value) { showError(new UserMessage("There is no case folder to import yet.")); return; }
      importBtn.disabled = true;
      try {
        const c = await apiJson<CaseSummary>("POST", "/api/cases/import", { folder: folder.value });
        location.hash = `#/case/${c.id}/contents`;
      } catch (e) { showError(e); } finally { importBtn.disabled = false; }
    });
    apiJson<{ folders: string[] }>("GET", "/api/case-folders").then((r) => {
      folder.replaceChildren(...r.folders.map((f) => h("option", { value: f }, f)));
      if (!r.folders.length) folder.append(h("option", { value: "" }, "No case folders"));
    }, showError);
    main.append(
      h("form", { class: "toolbar", onsubmit: create, "data-write": "" }, title, h("button", { class: "btn primary", type: "submit", "data-testid": "create-case" }, "Create case")),
      h("div", { class: "toolbar", "data-write": "" }, folder, importBtn),
      zipImportForm());
  } else {
    main.append(h("p", { class: "muted", "data-testid": "read-only-note" }, "Read-only: you are logged in as a reviewer."));
  }
  load();
}

// ---- Case view ---------------------------------------------------------------------------
// View changes and pictures shown, with their time: the e2e test reads it to measure how soon
// a touch shows a new picture (window.cfRenderTimeline).
const timeline: { what: string; t: number; size: string }[] = [];
(window as unknown as { cfRenderTimeline: typeof timeline }).cfRenderTimeline = timeline;
// Every wanted view (case view and fused view) gets the next number; the picture shown carries
// the number of the view it shows (img data-seq), so bench/ui_latency.mjs can tell a picture of
// the touched view from an older one still arriving (window.cfViewSeq()).
let viewSeq = 0;
(window as unknown as { cfViewSeq: () => number }).cfViewSeq = () => viewSeq;
interface View { preset: string; opacity: number; orbit: Orbit; tf: TfJson | null; brainOnly: boolean; seq?: number }
interface VolumeGeometry { center_lps_mm: Vec3; radius_mm: number; dims?: number[]; spacing_mm?: number[]; brain?: { center_lps_mm: Vec3; radius_mm: number } | null }
// Model points picked in the 3D view, waiting for their twin on the photo (per case, this tab).
const pendingModelPoints = new Map<number, Vec3[]>();
const BRAIN_PRESETS = new Set(["cortex_t1", "surface_white"]);

const CASE_TABS: [string, string][] = [["view", "3D view"], ["contents", "Contents"], ["plan", "Preoperative"], ["photo", "Photo & marks"], ["fused", "Fused"], ["tracker", "Tracker"], ["audit", "Audit trail"]];

/** The case's header (back, title, state) and its sub-screens; `onCase` gets the record, `onMissing`
 *  runs when it cannot be read (after the banner). */
function caseScreen(id: number, sub: string): void {
  // One row: back, the title and its state, then the case's screens (keeps the picture tall at 1280x800).
  const header = h("div", { class: "toolbar case-head" }, h("a", { class: "btn", href: "#/cases" }, "‹ Cases"),
    h("h1", { class: "grow case-title", "data-testid": "case-title" }, `Case ${id}`));
  const subtabs = h("div", { class: "subtabs" }, ...CASE_TABS.map(([key, label]) =>
    h("a", { class: `btn${key === sub ? " active" : ""}`, href: key === "view" ? `#/case/${id}` : `#/case/${id}/${key}`, "data-testid": `case-tab-${key}` }, label)));
  header.append(subtabs);
  main.append(header);
  const body = h("div", { class: "case-body" });
  main.append(body);
  let alive = true;
  leaveScreen = () => { alive = false; };
  const missing = (e: unknown) => {
    if (!alive) return;
    showError(e);
    body.replaceChildren(h("p", { class: "muted", "data-testid": "case-missing" },
      "This case could not be opened. Go back to the cases and pick another, or create one."));
  };
  const got = (c: CaseRecord) => {
    header.querySelector("h1")!.textContent = c.title || `Case ${id}`;
    header.querySelector("h1")!.after(h("span", { class: "badge", "data-testid": "case-state" }, c.state.replace(/_/g, " ")));
  };
  if (sub === "contents") caseContents(id, body, () => alive, got, missing);
  else if (sub === "audit") caseAudit(id, body, () => alive, got, missing);
  else if (sub === "plan") {
    apiJson<CaseRecord>("GET", `/api/cases/${id}`).then((c) => { if (alive) got(c); }, missing);
    planScreen(id, body, { alive: () => alive, writable: canWrite(session), showError,
      onLeave: (f) => { const prev = leaveScreen; leaveScreen = () => { prev?.(); f(); }; },
      onJob: (f) => { const g = (j: Job) => f(j as PlanJob); jobSubscribers.add(g); return () => { jobSubscribers.delete(g); }; } });
  } else if (sub === "photo") casePhoto(id, body, () => alive, got, missing, (f) => { const prev = leaveScreen; leaveScreen = () => { prev?.(); f(); }; });
  else if (sub === "tracker") {
    apiJson<CaseRecord>("GET", `/api/cases/${id}`).then((c) => { if (alive) got(c); }, missing);
    trackerScreen(id, body, { alive: () => alive, writable: canWrite(session), showError, showNotice, onLeave: (f) => { const prev = leaveScreen; leaveScreen = () => { prev?.(); f(); }; } });
  } else if (sub === "fused") caseFused(id, body, () => alive, got, missing, (f) => { const prev = leaveScreen; leaveScreen = () => { prev?.(); f(); }; });
  else caseView(id, body, () => alive, got, missing, (f) => { const prev = leaveScreen; leaveScreen = () => { prev?.(); f(); }; });
}

type Alive = () => boolean;

function caseContents(id: number, body: HTMLElement, alive: Alive, got: (c: CaseRecord) => void, missing: (e: unknown) => void): void {
  body.append(h("p", { class: "muted" }, "Loading…"));
  apiJson<CaseRecord>("GET", `/api/cases/${id}`).then((c) => {
    if (!alive()) return;
    got(c);
    const vols = c.volumes ?? [], photos = c.photos ?? [];
    const parts: HTMLElement[] = [
      h("ul", { class: "holdings", "data-testid": "case-holdings" }, ...holdings(c).map((l) => h("li", {}, l))),
      h("h2", {}, "Patient"), h("p", { "data-testid": "case-patient" }, patientLine(c.patient)),
      h("p", { class: "muted" }, `Case uid ${c.uid} · created ${fmtTime(c.created_utc)} · changed ${fmtTime(c.updated_utc)}`),
      h("h2", {}, "Volumes"),
      vols.length ? table(["modality", "file", "size", "sha256", "added"],
        vols.map((v) => [v.modality, v.original_name, fmtBytes(v.size_bytes), v.sha256.slice(0, 12), fmtTime(v.created_utc)]), "case-volumes")
        : h("p", { class: "muted" }, "None."),
      h("h2", {}, "Photos"),
      photos.length ? table(["file", "size (px)", "sha256", "added"],
        photos.map((p) => [p.original_name, p.intrinsics?.width ? `${p.intrinsics.width}x${p.intrinsics.height}` : "–", p.sha256.slice(0, 12), fmtTime(p.created_utc)]), "case-photos")
        : h("p", { class: "muted" }, "None."),
      h("h2", {}, "Landmarks"),
      c.landmarks?.points.length ? table(["name", "model (mm)", "photo (px)"],
        c.landmarks.points.map((p) => [p.name, p.world_mm.map((v) => v.toFixed(1)).join(", "), p.pixel.map((v) => v.toFixed(1)).join(", ")]), "case-landmarks")
        : h("p", { class: "muted" }, "None."),
      h("h2", {}, "ROI"),
      h("p", { "data-testid": "case-roi" }, c.roi ? `${c.roi.roi.type ?? "spline"}, ${c.roi.roi.points?.length ?? 0} control points, revision ${c.roi.revision}` : "None."),
      h("h2", {}, "Registrations"),
      c.registrations?.length ? table(["run", "status", "NMI", "time", "evaluations", "started", "error"], registrationRows(c.registrations), "case-registrations")
        : h("p", { class: "muted" }, "None."),
    ];
    if (c.results?.length) parts.push(h("h2", {}, "Results"), table(["kind", "name", "type", "registration"],
      c.results.map((r) => [r.kind, r.name, r.media_type, r.registration_id !== null ? `#${r.registration_id}` : ""]), "case-results"));
    if (canWrite(session)) {
      const reg = h("button", { class: "btn primary", "data-testid": "case-register" }, "Start registration");
      const ready = vols.length > 0 && photos.length > 0;
      reg.disabled = !ready;
      reg.addEventListener("click", async () => {
        reg.disabled = true;
        try {
          const j = await apiJson<Job>("POST", "/api/jobs", { kind: "register", params: { case_id: id } });
          upsertJob(j);
          location.hash = "#/jobs";
        } catch (e) { showError(e); reg.disabled = false; }
      });
      // Planning (the `plan` job: brain mask, surface, CT/fMRI on the T1), its progress on the Jobs screen.
      const plan = h("button", { class: "btn", "data-testid": "case-plan" }, "Start planning");
      plan.disabled = !vols.some((x) => x.modality === "T1");
      plan.addEventListener("click", async () => {
        plan.disabled = true;
        try {
          const j = await apiJson<Job>("POST", "/api/jobs", { kind: "plan", params: { case_id: id } });
          upsertJob(j);
          location.hash = "#/jobs";
        } catch (e) { showError(e); plan.disabled = false; }
      });
      parts.unshift(h("div", { class: "toolbar", "data-write": "" }, reg, plan,
        h("span", { class: "muted" }, ready ? "Registers the case's volume with its photo." : "Needs a volume and a photo first.")));
      parts.push(h("h2", {}, "Add data"), uploadForms(id));
    }
    // Export (everyone who may read) and the workflow state (writers: one step forward or back to any earlier one).
    const exp = h("button", { class: "btn", "data-testid": "case-export" }, "Export zip");
    exp.addEventListener("click", () => exportCase(id, exp));
    const row = h("div", { class: "toolbar" }, exp);
    if (canWrite(session)) {
      const st = h("select", { class: "field", "data-testid": "case-state-select", "aria-label": "Workflow state" },
        ...STATES.map((x) => h("option", { value: x }, x.replace(/_/g, " "))));
      st.value = c.state;
      const set = h("button", { class: "btn", "data-testid": "case-state-set", "data-write": "" }, "Set state");
      set.addEventListener("click", async () => {
        set.disabled = true;
        try { await apiJson("POST", `/api/cases/${id}/state`, { state: st.value }); route(); } catch (e) { showError(e); set.disabled = false; }
      });
      row.append(h("span", { class: "muted" }, "Workflow"), st, set);
    }
    parts.unshift(row);
    body.replaceChildren(...parts);
  }, missing);
}

/** Import a case zip (written by Export, or a plain case folder zipped) into the store. */
function zipImportForm(): HTMLElement {
  const file = h("input", { type: "file", class: "field grow", accept: ".zip,application/zip", "data-testid": "import-zip-file" });
  const btn = h("button", { class: "btn", type: "button", "data-testid": "import-zip" }, "Import zip");
  btn.addEventListener("click", async () => {
    const f = file.files?.[0];
    if (!f) { showError(new UserMessage("Choose the case zip first (written by Export, or a case folder zipped).")); return; }
    if (!/\.zip$/i.test(f.name)) { showError(new UserMessage(`${f.name}: not a .zip file. Choose the case zip written by Export.`)); return; }
    btn.disabled = true;
    try {
      const c = await apiUpload<CaseSummary>(`/api/cases/import-zip?name=${encodeURIComponent(f.name)}`, f);
      location.hash = `#/case/${c.id}/contents`;
    } catch (e) { showError(e); } finally { btn.disabled = false; }
  });
  return h("div", { class: "toolbar", "data-write": "" }, file, btn);
}

/** Downloads the case as a zip (GET /api/cases/N/export, with the session's token). */
async function exportCase(id: number, btn: HTMLButtonElement): Promise<void> {
  btn.disabled = true;
  try {
    const blob = await apiBlob(`/api/cases/${id}/export`);
    const url = URL.createObjectURL(blob);
    const a = h("a", { href: url, download: `case_${id}.zip` });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    showNotice(`Case ${id} exported (${fmtBytes(blob.size)}).`);
  } catch (e) { showError(e); } finally { btn.disabled = false; }
}

const STATES = ["new", "planned", "patient_registered", "photo_captured", "landmarks", "roi", "registered", "reviewed"];

/** Upload a volume (NIfTI, NRRD, MetaImage; with its modality) or a photo (PNG, JPEG; its
 *  camera from the picture's size and a focal length) into the case; the daemon checks both. */
function uploadForms(id: number): HTMLElement {
  const volFile = h("input", { type: "file", class: "field grow", accept: ".nii,.nii.gz,.nrrd,.mha,.gz", "data-testid": "upload-volume-file" });
  const volMod = h("select", { class: "field", "data-testid": "upload-volume-modality" }, ...["T1", "CT", "fMRI", "mask"].map((m) => h("option", { value: m }, m)));
  const volBtn = h("button", { class: "btn", type: "button", "data-testid": "upload-volume" }, "Upload volume");
  const photoFile = h("input", { type: "file", class: "field grow", accept: "image/png,image/jpeg,.png,.jpg,.jpeg", "data-testid": "upload-photo-file" });
  const focal = h("input", { type: "number", class: "field narrow", min: 10, max: 100000, step: 1, value: 1400, "data-testid": "upload-photo-focal", title: "focal length (px)" });
  const photoBtn = h("button", { class: "btn", type: "button", "data-testid": "upload-photo" }, "Upload photo");
  const captureBtn = h("button", { class: "btn", type: "button", "data-testid": "capture-photo" }, "Capture from camera");
  const status = h("p", { class: "muted", "data-testid": "upload-status" }, "");
  const busy = async (btn: HTMLButtonElement, what: string, f: () => Promise<void>) => {
    btn.disabled = true;
    status.textContent = `${what}…`;
    try { await f(); status.textContent = ""; route(); } catch (e) { status.textContent = ""; showError(e); } finally { btn.disabled = false; }
  };
  volBtn.addEventListener("click", () => {
    const f = volFile.files?.[0];
    if (!f) { showError(new UserMessage("Choose the volume file first (NIfTI .nii/.nii.gz, NRRD or MetaImage .mha).")); return; }
    busy(volBtn, `Uploading ${f.name} (${fmtBytes(f.size)})`, async () => {
      try {
        await apiUpload(`/api/cases/${id}/volumes?name=${encodeURIComponent(f.name)}&modality=${encodeURIComponent(volMod.value)}`, f);
      } catch (e) { throw e instanceof ApiError ? new UserMessage(volumeRefusalNextStep(e.message)) : e; }
    });
  });
  photoBtn.addEventListener("click", () => {
    const f = photoFile.files?.[0];
    if (!f) { showError(new UserMessage("Choose the photo file first (PNG or JPEG).")); return; }
    busy(photoBtn, `Uploading ${f.name}`, async () => {
      if (!imageKind(new Uint8Array(await f.slice(0, 16).arrayBuffer())))
        throw new UserMessage(`photo ${f.name}: not a PNG or JPEG picture (its first bytes say otherwise). Choose the photo file itself.`);
      let bmp: ImageBitmap;
      try { bmp = await createImageBitmap(f); } catch { throw new UserMessage(`photo ${f.name}: the picture cannot be decoded (damaged or cut short).`); }
      const cam = defaultCamera(bmp.width, bmp.height, Number(focal.value) || 1400);
      bmp.close();
      await apiUpload(`/api/cases/${id}/photos?name=${encodeURIComponent(f.name)}&camera=${encodeURIComponent(JSON.stringify(cam))}`, f);
    });
  });
  // The cart's camera (POST /api/camera/capture answers the picture); the camera has no
  // calibration over the API, so its intrinsics are the picture's size and the focal length typed.
  captureBtn.addEventListener("click", () => {
    busy(captureBtn, "Taking a photo (the first one can take a few seconds)", async () => {
      const blob = await apiBlob("/api/camera/capture", fetch, "POST");
      let bmp: ImageBitmap;
      try { bmp = await createImageBitmap(blob); } catch { throw new UserMessage("The camera's picture cannot be decoded; try again, or pick a file."); }
      const cam = defaultCamera(bmp.width, bmp.height, Number(focal.value) || 1400);
      bmp.close();
      const name = `capture_${new Date().toISOString().replace(/[-:]/g, "").replace(/\..*$/, "")}.${blob.type === "image/png" ? "png" : "jpg"}`;
      await apiUpload(`/api/cases/${id}/photos?name=${encodeURIComponent(name)}&camera=${encodeURIComponent(JSON.stringify(cam))}`, blob);
    });
  });
  // From a USB stick (src/media.ts): the daemon lists the volume files and DICOM folders under
  // its media.removable_root; the chosen one is imported with the modality chosen above.
  const stickLook = h("button", { class: "btn", type: "button", "data-testid": "media-look" }, "Look on USB stick");
  const stickPick = h("select", { class: "field grow", "data-testid": "media-volume", hidden: true });
  const stickImport = h("button", { class: "btn", type: "button", "data-testid": "media-import", hidden: true }, "Import from stick");
  const stickLine = h("p", { class: "muted", "data-testid": "media-line" }, "");
  stickLook.addEventListener("click", async () => {
    stickLook.disabled = true;
    try {
      const a = await apiJson<MediaAnswer>("GET", "/api/media/volumes");
      stickLine.textContent = mediaLine(a);
      stickPick.replaceChildren(...mediaChoices(a).map((c) => h("option", { value: c.value }, c.label)));
      stickPick.hidden = stickImport.hidden = !a.volumes.length;
    } catch (e) { showError(e); } finally { stickLook.disabled = false; }
  });
  stickImport.addEventListener("click", () => {
    const chosen = stickPick.value;
    if (!chosen) { showError(new UserMessage("Choose a volume on the stick first (Look on USB stick).")); return; }
    busy(stickImport, `Importing ${chosen} from the stick as ${volMod.value}`, async () => {
      const r = mediaImport(id, chosen, volMod.value);
      try { await apiJson("POST", r.path, r.body); } catch (e) { throw e instanceof ApiError ? new UserMessage(volumeRefusalNextStep(e.message)) : e; }
      showNotice(`Imported ${chosen} from the USB stick as ${volMod.value}.`);
    });
  });
  return h("div", { class: "uploads", "data-write": "" },
    h("div", { class: "toolbar" }, volFile, volMod, volBtn),
    h("div", { class: "toolbar" }, stickLook, stickPick, stickImport), stickLine,
    h("div", { class: "toolbar" }, photoFile, h("label", { class: "muted" }, "focal px"), focal, photoBtn),
    h("div", { class: "toolbar" }, captureBtn), status);
}

type OnLeave = (f: () => void) => void;

/** The case's newest photo with its landmark twins and the ROI: view for everyone, edit by touch
 *  for writers (drag a landmark's photo pixel; tap to add ROI points, drag, delete), saved as a
 *  new revision (the daemon validates against the photo). */
function casePhoto(id: number, body: HTMLElement, alive: Alive, got: (c: CaseRecord) => void, missing: (e: unknown) => void, onLeave: OnLeave): void {
  body.append(h("p", { class: "muted" }, "Loading…"));
  const writer = canWrite(session);
  apiJson<CaseRecord>("GET", `/api/cases/${id}`).then(async (c) => {
    if (!alive()) return;
    got(c);
    const photos = [...(c.photos ?? [])].sort((a, b) => b.id - a.id);
    if (!photos.length) {
      const msg = h("p", { class: "muted", "data-testid": "no-photo" }, writer ? "No photo yet: capture one with the camera here (Live view, then Capture), or add a file in Contents." : "No photo yet.");
      if (!writer) { body.replaceChildren(msg); return; }
      // The camera's live view and Capture (src/live_view.ts); stopped when the screen is left.
      const liveStage = h("div", { class: "photo-stage", "data-testid": "photo-stage" });
      const liveSide = h("aside", { class: "controls" }, msg);
      body.replaceChildren(h("div", { class: "case-layout" }, liveStage, liveSide));
      onLeave(mountLiveView(id, liveStage, liveSide, () => route(), showError).stop);
      return;
    }
    const photo = photos[0];
    const W = photo.intrinsics?.width ?? 640, H = photo.intrinsics?.height ?? 480;
    // The daemon's copy of unsaved marks (marks_draft.ts), asked while the photo loads.
    const daemonDraft = writer ? loadDaemonDraft(draftRequest, id, photo.id, session.user) : Promise.resolve(undefined);
    let blob: Blob;
    try { blob = await apiBlob(`/api/cases/${id}/photos/${photo.id}`); } catch (e) { showError(e); return; }
    const kept = await daemonDraft;
    if (!alive()) return;
    const url = URL.createObjectURL(blob);
    onLeave(() => URL.revokeObjectURL(url));
    const NS = "http://www.w3.org/2000/svg";
    const svg = document.createElementNS(NS, "svg");
    svg.setAttribute("viewBox", `-0.5 -0.5 ${W} ${H}`);
    svg.setAttribute("preserveAspectRatio", "xMidYMid meet");
    svg.setAttribute("class", "marks");
    svg.setAttribute("data-testid", "photo-marks");
    const stage = h("div", { class: "photo-stage", "data-testid": "photo-stage" },
      h("img", { class: "photo", src: url, alt: `Photo ${photo.original_name}`, draggable: "false", "data-testid": "photo-image" }));
    stage.append(svg);

    // State: the landmark pairs (the world point stays, the photo pixel can move) and the ROI.
    let lms = (c.landmarks?.points ?? []).map((p) => ({ name: p.name, world_mm: p.world_mm, pixel: [p.pixel[0], p.pixel[1]] as Px }));
    let roi: Px[] = (c.roi?.roi.points ?? []).map((p) => [p[0], p[1]] as Px);
    const tension = c.roi?.roi.tension ?? 0;
    let mode: "landmarks" | "roi" = "landmarks";
    let sel = -1;
    let dirtyL = false, dirtyR = false;
    // Unsaved edits kept in this tab and by the daemon (marks_draft.ts, 7.47): the newer of the
    // two restored after a reload, a login screen or a restart of the browser, with a line saying
    // they are not saved yet; kept again on every draw below (the daemon's 500 ms after the last).
    const lmRev = c.landmarks?.revision ?? null, roiRev = c.roi?.revision ?? null;
    const picked = writer ? pickDraft(marksDrafts.load(id, photo.id, session.user), kept?.draft ?? null) : null;
    const draft = picked ? withoutSavedParts(picked.draft, { landmarks: c.landmarks ? lms : null, roi: c.roi ? roi : null }) : null;
    const sync = writer ? new DaemonDraftSync(id, draftRequest) : null;
    sync?.assume(kept === undefined ? undefined : kept.body);
    if (sync) onLeave(() => sync.dispose());
    if (draft?.landmarks) { lms = draft.landmarks.map((l) => ({ name: l.name, world_mm: l.world_mm, pixel: [l.pixel[0], l.pixel[1]] as Px })); dirtyL = true; }
    if (draft?.roi) { roi = draft.roi.map((p) => [p[0], p[1]] as Px); dirtyR = true; }
    const restored = h("p", { class: "banner warn restored", role: "status", "data-testid": "marks-restored", hidden: !draft },
      draft ? restoredText(draft, { landmarks: lmRev, roi: roiRev }, picked?.source) : "");
    if (draft) restored.dataset.source = picked?.source;
    if (alive()) leaveGuard.set(() => (alive() ? unsavedMarksText(dirtyL, dirtyR) : null), () => { marksDrafts.drop(id); void sync?.discard(); });
    const info = h("p", { class: "muted", "data-testid": "photo-info" });
    const list = h("div", { class: "list compact", "data-testid": "landmark-list" });
    // The initial alignment of the pairs as they are on the screen (saved or not), asked after
    // each change (src/initial_alignment.ts): the RMS here, each pair's error in its row, the
    // model points projected with that pose on the photo.
    const alignLine = h("p", { class: "align-line", "data-testid": "alignment", role: "status" });
    let errSpans: HTMLElement[] = [];
    const paintAlignment = () => {
      const a = aligner.alignment;
      alignLine.textContent = alignmentHeadline(a, aligner.pairCount, aligner.error);
      alignLine.dataset.state = a ? (a.warning ? "warning" : "ok") : aligner.error ? "refused" : aligner.pairCount < 4 ? "too-few" : "computing";
      if (a) alignLine.dataset.rmsPx = a.rms_px.toFixed(3); else delete alignLine.dataset.rmsPx;
      errSpans.forEach((sp, i) => {
        sp.textContent = pairErrorText(a, i);
        const e = a?.pairs[i]?.error_px;
        sp.classList.toggle("high", e !== null && e !== undefined && e > highErrorPx(W));
      });
    };
    const aligner = new AlignmentFetcher(id, () => { if (alive()) { paintAlignment(); draw(); } });
    const realign = () => { void aligner.update(lms, photo.id); };
    const saveL = h("button", { class: "btn primary", "data-testid": "save-landmarks", "data-write": "" }, "Save landmarks");
    const saveR = h("button", { class: "btn primary", "data-testid": "save-roi", "data-write": "" }, "Save ROI");
    const delR = h("button", { class: "btn", "data-testid": "roi-delete", "data-write": "" }, "Delete point");
    const clearR = h("button", { class: "btn", "data-testid": "roi-clear", "data-write": "" }, "Clear ROI");
    const modeBox = h("div", { class: "choices" });
    const lmPanel = h("div", {}, h("h2", {}, "Landmark pairs"), alignLine, list, writer ? h("div", { class: "toolbar" }, saveL) : "",
      h("p", { class: "muted" }, writer ? "Drag a numbered mark to move the photo twin of that landmark; its point on the model stays. A new pair: Pick landmark in the 3D view, tap the model, then tap its twin here." : "Read-only."));
    const roiPanel = h("div", {}, h("h2", {}, "ROI (closed spline)"),
      writer ? h("div", { class: "choices" }, delR, clearR, saveR) : "",
      h("p", { class: "muted" }, writer ? "Tap on the photo to add a control point (it goes into the nearest edge), drag one to move it, tap it and Delete point to remove it." : "Read-only."));
    const side = h("aside", { class: "controls" }, restored, h("h2", {}, "Mark"), modeBox, lmPanel, roiPanel, info);
    body.replaceChildren(h("div", { class: "case-layout" }, stage, side));
    if (writer) onLeave(mountLiveView(id, stage, side, () => route(), showError).stop); // a new photo: live view, Capture

    const scale = () => { const r = svg.getBoundingClientRect(); return Math.min(r.width / W, r.height / H) || 1; };
    const toPx = (e: PointerEvent): Px => {
      const m = svg.getScreenCTM();
      if (!m) return [0, 0];
      const p = new DOMPoint(e.clientX, e.clientY).matrixTransform(m.inverse());
      return [p.x, p.y];
    };
    const draw = () => {
      const k = scale(), r = 14 / k, hit = 24 / k;
      svg.replaceChildren();
      const el = (tag: string, attrs: Record<string, string | number>) => { const x = document.createElementNS(NS, tag); for (const [a, v] of Object.entries(attrs)) x.setAttribute(a, String(v)); svg.append(x); return x; };
      if (roi.length) {
        el("path", { d: cardinalPath(roi, tension), class: `roi-path${mode === "roi" ? " active" : ""}`, "stroke-width": 3 / k, "data-testid": "roi-path" });
        if (mode === "roi") roi.forEach((p, i) => el("circle", { cx: p[0], cy: p[1], r: i === sel ? r * 1.2 : r * 0.8, class: `roi-point${i === sel ? " sel" : ""}`, "stroke-width": 2 / k }));
      }
      const al = mode === "landmarks" ? aligner.alignment : null;
      if (al && al.pairs.length === lms.length) al.pairs.forEach((p, i) => {
        // The model point projected with the initial pose: a cross, joined to its twin.
        if (!p.projected_pixel) return;
        const [u, v] = p.projected_pixel, c = 8 / k;
        const cls = `lm-proj${(p.error_px ?? 0) > highErrorPx(W) ? " high" : ""}`;
        el("line", { x1: lms[i].pixel[0], y1: lms[i].pixel[1], x2: u, y2: v, class: cls, "stroke-width": 1.5 / k });
        el("path", { d: `M${u - c},${v - c} L${u + c},${v + c} M${u - c},${v + c} L${u + c},${v - c}`, class: cls, "stroke-width": 2.5 / k, "data-testid": "lm-projected" });
      });
      lms.forEach((l, i) => {
        el("circle", { cx: l.pixel[0], cy: l.pixel[1], r: mode === "landmarks" && i === sel ? r * 1.2 : r, class: `lm${mode === "landmarks" && i === sel ? " sel" : ""}`, "stroke-width": 2 / k });
        const t = el("text", { x: l.pixel[0], y: l.pixel[1] + 5 / k, "font-size": 14 / k, class: "lm-label" });
        t.textContent = String(i + 1);
      });
      void hit;
      svg.dataset.landmarks = String(lms.length);
      svg.dataset.roiPoints = String(roi.length);
      svg.dataset.mode = mode;
      saveL.disabled = !dirtyL;
      saveR.disabled = !dirtyR;
      if (writer && alive()) {
        const kd = marksDrafts.keep(id, photo.id, session.user, dirtyL ? { points: lms, fromRevision: lmRev } : null, dirtyR ? { points: roi, fromRevision: roiRev } : null);
        sync?.schedule(kd ? toDaemonBody(kd) : null);
      }
      if (!dirtyL && !dirtyR) restored.hidden = true;
      delR.disabled = mode !== "roi" || sel < 0;
      const waiting = (pendingModelPoints.get(id) ?? []).length;
      info.textContent = `${photo.original_name}, ${W}x${H} px · ${lms.length} landmark pairs · ROI ${roi.length} points${dirtyL || dirtyR ? " · unsaved changes" : ""}` +
        (waiting ? ` · ${waiting} model point${waiting > 1 ? "s" : ""} picked in the 3D view: tap the twin on the photo (Landmarks)` : "");
    };
    const drawList = () => {
      errSpans = [];
      list.replaceChildren(...lms.map((l, i) => {
        const name = h("input", { type: "text", class: "field grow", value: l.name, "aria-label": `landmark ${i + 1} name`, "data-testid": "landmark-name" });
        name.readOnly = !writer;
        name.addEventListener("input", () => { l.name = name.value; dirtyL = true; draw(); });
        const del = h("button", { class: "btn", "data-write": "", "data-testid": "landmark-delete" }, "Delete");
        del.addEventListener("click", () => { lms = lms.filter((_, k) => k !== i); sel = -1; dirtyL = true; drawList(); draw(); realign(); });
        errSpans[i] = h("span", { class: "lm-err small", "data-testid": "landmark-error" }, "");
        return h("div", { class: "lm-row", "data-testid": "landmark-row" }, h("strong", {}, String(i + 1)), name,
          h("span", { class: "muted small" }, `px ${l.pixel.map((v) => v.toFixed(0)).join(", ")}`), errSpans[i], writer ? del : "");
      }));
      errSpans.length = lms.length;
      paintAlignment();
    };
    const setMode = (m: "landmarks" | "roi") => {
      mode = m; sel = -1;
      modeBox.querySelectorAll("button").forEach((b) => b.classList.toggle("active", b.dataset.value === m));
      lmPanel.hidden = m !== "landmarks"; roiPanel.hidden = m !== "roi";
      draw();
    };
    modeBox.append(...(["landmarks", "roi"] as const).map((m) => h("button", { class: "btn", "data-value": m, "data-testid": `mode-${m}`, onclick: () => setMode(m) }, m === "roi" ? "ROI" : "Landmarks")));

    // Touch on the photo (writers): pick or move marks.
    let drag: number | null = null;
    svg.addEventListener("pointerdown", (e) => {
      if (!writer) return;
      const p = toPx(e), k = scale();
      if (mode === "landmarks") {
        sel = nearest(lms.map((l) => l.pixel), p, 28 / k);
        const waiting = pendingModelPoints.get(id) ?? [];
        if (sel < 0 && waiting.length) {
          // The twin of the model point picked in the 3D view: a new pair.
          const used = new Set(lms.map((l) => l.name));
          let n = lms.length + 1;
          while (used.has(`L${n}`)) n++;
          lms.push({ name: `L${n}`, world_mm: waiting[0], pixel: clampPx(p, W, H) });
          pendingModelPoints.set(id, waiting.slice(1));
          sel = lms.length - 1;
          dirtyL = true;
          drawList();
        }
        if (sel >= 0) drag = e.pointerId;
      } else {
        sel = nearest(roi, p, 28 / k);
        if (sel < 0) { const r = insertRoiPoint(roi, clampPx(p, W, H)); roi = r.points; sel = r.index; dirtyR = true; }
        drag = e.pointerId;
      }
      if (drag !== null) svg.setPointerCapture(e.pointerId);
      draw();
    });
    svg.addEventListener("pointermove", (e) => {
      if (drag !== e.pointerId || sel < 0) return;
      const p = clampPx(toPx(e), W, H);
      if (mode === "landmarks") { lms[sel].pixel = p; dirtyL = true; } else { roi[sel] = p; dirtyR = true; }
      draw();
    });
    const up = (e: PointerEvent) => { if (drag === e.pointerId) { drag = null; if (mode === "landmarks") { drawList(); realign(); } } };
    svg.addEventListener("pointerup", up);
    svg.addEventListener("pointercancel", up);
    delR.addEventListener("click", () => { if (sel >= 0) { roi = roi.filter((_, k) => k !== sel); sel = -1; dirtyR = true; draw(); } });
    clearR.addEventListener("click", () => { roi = []; sel = -1; dirtyR = true; draw(); });
    saveL.addEventListener("click", async () => {
      saveL.disabled = true;
      try {
        const r = await apiJson<{ revision: number }>("POST", `/api/cases/${id}/landmarks`,
          { landmarks: lms.map((l) => ({ label: l.name, world_mm: l.world_mm, pixel: l.pixel })), photo_id: photo.id });
        dirtyL = false;
        showNotice(`Landmarks saved (revision ${r.revision}).`);
        draw();
        void sync?.flush(); // the daemon's draft follows at once
        realign();
      } catch (e) { showError(new UserMessage(saveFailedText("landmarks", e, plainMessage))); draw(); }
    });
    saveR.addEventListener("click", async () => {
      saveR.disabled = true;
      try {
        const r = await apiJson<{ revision: number }>("POST", `/api/cases/${id}/roi`,
          { points: roi, tension, type: "closed-cardinal-spline", photo_id: photo.id });
        dirtyR = false;
        showNotice(`ROI saved (revision ${r.revision}).`);
        draw();
        void sync?.flush();
      } catch (e) { showError(new UserMessage(saveFailedText("ROI", e, plainMessage))); draw(); }
    });
    const ro = new ResizeObserver(() => draw());
    ro.observe(svg as unknown as Element);
    onLeave(() => ro.disconnect());
    drawList();
    setMode("landmarks");
    realign();
  }, missing);
}

/** The newest successful registration: the model rendered from its pose with the photo's camera,
 *  laid over the photo at an adjustable opacity, with the run's figures. */
function caseFused(id: number, body: HTMLElement, alive: Alive, got: (c: CaseRecord) => void, missing: (e: unknown) => void, onLeave: OnLeave): void {
  body.append(h("p", { class: "muted" }, "Loading…"));
  interface RegFull { id: number; status: string; nmi?: number; seconds?: number; evaluations?: number; photo_id?: number;
                      final_pose?: { T_camera_from_world: number[][] }; initial_pose?: { T_camera_from_world: number[][] } }
  Promise.all([apiJson<CaseRecord>("GET", `/api/cases/${id}`), apiJson<{ registrations: RegFull[] }>("GET", `/api/cases/${id}/registrations`)]).then(async ([c, rr]) => {
    if (!alive()) return;
    got(c);
    const ok = rr.registrations.filter((r) => r.status === "succeeded" && r.final_pose?.T_camera_from_world).sort((a, b) => b.id - a.id);
    if (!ok.length) { body.replaceChildren(h("p", { class: "muted", "data-testid": "no-result" }, "No successful registration yet. Start one in Contents; its result is shown here.")); return; }
    const reg = ok[0];
    const photo = (c.photos ?? []).find((p) => p.id === reg.photo_id) ?? [...(c.photos ?? [])].sort((a, b) => b.id - a.id)[0];
    if (!photo?.intrinsics?.width) { body.replaceChildren(h("p", { class: "muted" }, "The registration's photo is missing.")); return; }
    const K = photo.intrinsics as { width: number; height: number };
    const k = Math.min(1, 1280 / K.width, 1024 / K.height);
    const w = Math.round(K.width * k), hh = Math.round(K.height * k);
    const urls: string[] = [];
    onLeave(() => urls.forEach((u) => URL.revokeObjectURL(u)));
    const photoImg = h("img", { class: "fused-photo", alt: "Photo", draggable: "false", "data-testid": "fused-photo" });
    const modelImg = h("img", { class: "fused-model", alt: "Model from the registered pose", draggable: "false", "data-testid": "fused-model" });
    const stage = h("div", { class: "photo-stage fused", "data-testid": "fused-stage" }, photoImg, modelImg);
    const opacityOut = h("span", { class: "value" }, "50 %");
    const opacity = h("input", { type: "range", min: 0, max: 100, step: 5, value: 50, class: "slider", "data-testid": "fused-opacity" });
    const presetBox = h("div", { class: "choices" });
    const info = h("p", { class: "muted", "data-testid": "fused-info" },
      `Registration #${reg.id}: NMI ${reg.nmi?.toFixed(4) ?? "–"}, ${reg.seconds?.toFixed(1) ?? "–"} s, ${reg.evaluations ?? "–"} evaluations; photo ${photo.original_name}.`);
    body.replaceChildren(h("div", { class: "case-layout" }, stage, h("aside", { class: "controls" },
      h("h2", {}, "Model opacity ", opacityOut), opacity, h("h2", {}, "Model"), presetBox, info)));
    const setOpacity = () => { modelImg.style.opacity = String(Number(opacity.value) / 100); opacityOut.textContent = `${opacity.value} %`; };
    opacity.addEventListener("input", setOpacity);
    setOpacity();
    try {
      const pb = await apiBlob(`/api/cases/${id}/photos/${photo.id}`);
      const u = URL.createObjectURL(pb); urls.push(u); photoImg.src = u;
    } catch (e) { showError(e); }
    // Without a brain surface: one plain render a view. It carries its view number like every
    // picture (img data-seq), and an answer for an older tap arriving late is dropped.
    const renderModel = async (preset: string) => {
      presetBox.querySelectorAll("button").forEach((b) => b.classList.toggle("active", b.dataset.value === preset));
      const seq = ++viewSeq;
      try {
        const req = { width: w, height: hh, preset, camera: photo.intrinsics as unknown, T_camera_from_world: reg.final_pose!.T_camera_from_world };
        let r: RenderedImage;
        try {
          r = await apiRender(req);
        } catch (e) {
          // The daemon at commit ccf80fe reads `camera` as a case.json (`{camera: {...}}`) and
          // refuses the intrinsics themselves with 'missing "camera"': ask again in that shape
          // (either form works, whichever the daemon takes).
          if (!(e instanceof ApiError && e.status === 400 && /missing "camera"/.test(e.message))) throw e;
          r = await apiRender({ ...req, camera: { camera: photo.intrinsics } });
        }
        if (!alive() || seq !== viewSeq) return;
        const u = URL.createObjectURL(r.blob); urls.push(u); modelImg.src = u;
        modelImg.dataset.full = "true";
        modelImg.dataset.preset = preset;
        modelImg.dataset.seq = String(seq);
      } catch (e) { showError(e); }
    };
    presetBox.append(...["cortex_t1", "surface_white"].map((p) => h("button", { class: "btn", "data-value": p, onclick: () => renderModel(p) }, p.replace(/_/g, " "))));
    // With a plan's brain surface: the photo on the model (POST /api/cases/N/fused: the textured
    // surface over the volume rendering, the slider its opacity), turned by dragging, and
    // "Camera view" back to the registered camera (GET /api/cases/N/fused/camera).
    if (!(c.results ?? []).some((r) => r.kind === "plan_brain_surface")) {
      info.append(h("span", { "data-testid": "fused-no-surface" }, " No brain surface yet (run planning): the model is shown over the photo."));
      renderModel("cortex_t1");
      return;
    }
    const T0 = reg.final_pose!.T_camera_from_world;
    let T = T0, preset = "cortex_t1";
    // The multimodal volume under the photo (fused_modalities.ts): the T1 and the plan's CT /
    // fMRI on/off and weighted; only the modalities the plan has are offered.
    let layers = fusedLayers(c);
    const modalityBox = h("div", { "data-testid": "fused-modality-box" });
    let tagView: ReturnType<typeof mountTags> | null = null;
    const snapBtn = h("button", { class: "btn", "data-testid": "fused-camera-view" }, "Camera view");
    photoImg.hidden = true;
    modelImg.style.opacity = "1";
    stage.style.touchAction = "none";
    // The pictures (issue 7: a new picture within 150 ms of a touch): a quarter-size preview at
    // once while a finger moves (drag, pinch, sliders), the full size once it rests 200 ms; a
    // button shows the preview, then the full size. One stream per screen: the daemon gives up
    // an older full render when a newer view of it arrives (RenderScheduler overtake).
    interface FusedWant { req: Record<string, unknown>; layersShown: string; preset: string; seq: number }
    const stream = `fused-${Math.random().toString(36).slice(2, 10)}`;
    let lastWant = "";
    const fsched = new RenderScheduler<FusedWant>({
      // The preview also steps 2 mm along the rays (half the samples of the full picture's 1 mm).
      render: (fv, size) => apiPostBlob(`/api/cases/${id}/fused`, { ...fv.req, width: size.width, height: size.height, stream,
                                                                    ...(size.width < w ? { sample_mm: 2 } : {}) }),
      onImage: (blob, fv, _size, full) => {
        if (!alive()) return;
        modelImg.dataset.layers = fv.layersShown;
        modelImg.dataset.seq = String(fv.seq);
        const u = URL.createObjectURL(blob as Blob); urls.push(u); modelImg.src = u;
        while (urls.length > 12) URL.revokeObjectURL(urls.splice(1, 1)[0]);  // [0] is the photo's; the last few stay readable
        modelImg.dataset.full = String(full);
        modelImg.dataset.preset = fv.preset;
        modelImg.dataset.textured = "true";
        tagView?.redraw();
      },
      onError: (e) => {
        if (!alive()) return;
        if (layers && layersNeedGl(plainMessage(e))) {  // a CPU-only daemon: the T1 alone, and why
          layers = null;
          modalityBox.replaceChildren(h("p", { class: "muted", "data-testid": "fused-modality-note" }, "CT and fMRI need the GL renderer, which this cart does not have: the photo is shown over the T1 alone."));
          renderTextured(false, true);
          return;
        }
        showError(e);
      },
      sizes: () => ({ full: { width: w, height: hh }, preview: { width: Math.max(16, Math.round(w / 4)), height: Math.max(16, Math.round(hh / 4)) } }),
      overtake: true,
      isSuperseded: (e) => e instanceof ApiError && e.code === "superseded",
    });
    let atCameraPose: number[][] | null = null;  // the registered camera as GET .../fused/camera answered it
    /** The view changed: `interactive` while a finger moves, else a step (button, let go). The
     *  same view asked for again (a slider let go where it was last moved) makes nothing new. */
    const renderTextured = (interactive = false, force = false) => {
      presetBox.querySelectorAll("button").forEach((b) => b.classList.toggle("active", b.dataset.value === preset));
      stage.dataset.atCamera = String(T === T0 || atCameraPose === T);
      const req = fusedRequest({ width: w, height: hh, preset, camera: photo.intrinsics, T_camera_from_world: T,
                                 surfaceOpacity: Number(opacity.value) / 100 }, layers) as unknown as Record<string, unknown>;
      const key = JSON.stringify(req);
      if (!interactive && !force && key === lastWant) return;
      lastWant = key;
      const fv: FusedWant = { req, preset, seq: ++viewSeq,
                              layersShown: layers ? layers.filter((l) => l.visible && l.weight > 0).map((l) => l.name).join(",") : "t1" };
      if (interactive) fsched.interactive(fv); else fsched.soon(fv);
    };
    if (layers) modalityBox.replaceChildren(h("h2", {}, "Modalities"), new FusedModalityPanel(layers, (final) => renderTextured(!final)).el);
    opacity.removeEventListener("input", setOpacity);
    opacity.addEventListener("input", () => { opacityOut.textContent = `${opacity.value} %`; renderTextured(true); });
    opacity.addEventListener("change", () => renderTextured(false));
    opacityOut.textContent = `${opacity.value} %`;
    presetBox.replaceChildren(...["cortex_t1", "surface_white"].map((p) => h("button", { class: "btn", "data-value": p, onclick: () => { preset = p; renderTextured(false); } }, p.replace(/_/g, " "))));
    snapBtn.addEventListener("click", async () => {
      try {
        const cam = await apiJson<{ T_camera_from_world: number[][] }>("GET", `/api/cases/${id}/fused/camera?registration_id=${reg.id}`);
        T = cam.T_camera_from_world;
        atCameraPose = T;
        pivot = pivot0;
        renderTextured(false, true);
      } catch (e) { showError(e); }
    });
    presetBox.after(modalityBox, h("h2", {}, "View"), h("div", { class: "choices" }, snapBtn),
                    h("p", { class: "muted" }, "Drag on the picture to turn the model; Camera view goes back to the photo's camera."));
    // Stimulation tags (src/tags.ts): placed on the photo at the registered camera, drawn in 3D.
    const atCam = () => stage.dataset.atCamera === "true";
    tagView = mountTags({ caseId: id, registrationId: reg.id, stage, panel: info.parentElement as HTMLElement, K: photo.intrinsics as unknown as Intrinsics,
                          viewW: w, viewH: hh, pose: () => T, atCamera: atCam, toCamera: async () => { snapBtn.click(); await new Promise((r) => setTimeout(r, 0)); },
                          canWrite: !document.body.classList.contains("read-only"), showError });
    // Drag: 0.3 degrees a pixel about the point the camera looks at (at the registered distance).
    let drag: { x: number; y: number; T: number[][]; moving: boolean } | null = null;
    const pivot0 = Math.abs(T0[2][3]) > 1 ? Math.hypot(T0[0][3], T0[1][3], T0[2][3]) : 300;
    let pivot = pivot0; // a pinch brings the camera closer to it
    // The model turns while the finger moves (a preview each move, the full size when it rests);
    // a tap (under 8 px) turns nothing (it may place a tag).
    stage.addEventListener("pointerdown", (e) => { drag = { x: e.clientX, y: e.clientY, T, moving: false }; stage.setPointerCapture(e.pointerId); });
    stage.addEventListener("pointermove", (e) => {
      if (!drag || fingers.size > 1) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      if (!drag.moving && Math.hypot(dx, dy) < 8) return;
      drag.moving = true;
      T = orbitCamera(drag.T, -0.3 * dx, 0.3 * dy, pivot);
      renderTextured(true);
    });
    stage.addEventListener("pointerup", () => { drag = null; });
    // Two fingers: pinch to zoom, move both to pan (fused_pose.ts pinchPan), live while they move;
    // the pivot's new depth is kept when they lift.
    const fingers = new Map<number, { x: number; y: number }>();
    let pinch: { d0: number; cx: number; cy: number; T: number[][]; pivot: number; z: { T: number[][]; pivotDepthMm: number } | null } | null = null;
    const spread = () => { const [a, b] = [...fingers.values()]; return { d: Math.hypot(a.x - b.x, a.y - b.y), cx: (a.x + b.x) / 2, cy: (a.y + b.y) / 2 }; };
    stage.addEventListener("pointerdown", (e) => {
      fingers.set(e.pointerId, { x: e.clientX, y: e.clientY });
      if (fingers.size === 2) { const s = spread(); pinch = { d0: Math.max(1, s.d), cx: s.cx, cy: s.cy, T, pivot, z: null }; drag = null; }
    });
    stage.addEventListener("pointermove", (e) => {
      if (!fingers.has(e.pointerId)) return;
      fingers.set(e.pointerId, { x: e.clientX, y: e.clientY });
      if (!pinch || fingers.size !== 2) return;
      const s = spread(), r = stage.getBoundingClientRect();
      const cssPerPx = Math.min(r.width / w, r.height / hh) || 1; // the picture is fitted (object-fit: contain)
      const fView = (photo.intrinsics as { fx: number }).fx * (w / K.width);
      pinch.z = pinchPan(pinch.T, s.d / pinch.d0, (s.cx - pinch.cx) / cssPerPx, (s.cy - pinch.cy) / cssPerPx, pinch.pivot, fView);
      T = pinch.z.T;
      renderTextured(true);
    });
    const lift = (e: PointerEvent) => {
      if (pinch?.z) pivot = pinch.z.pivotDepthMm;
      fingers.delete(e.pointerId);
      if (fingers.size < 2) pinch = null;
      drag = null; // the other finger's lift is no turn
    };
    stage.addEventListener("pointerup", lift);
    stage.addEventListener("pointercancel", lift);
    renderTextured(false, true);
  }, missing);
}

function caseAudit(id: number, body: HTMLElement, alive: Alive, got: (c: CaseRecord) => void, missing: (e: unknown) => void): void {
  body.append(h("p", { class: "muted" }, "Loading…"));
  Promise.all([apiJson<CaseRecord>("GET", `/api/cases/${id}`), apiJson<{ audit: AuditEntry[] }>("GET", `/api/cases/${id}/audit`)]).then(([c, a]) => {
    if (!alive()) return;
    got(c);
    body.replaceChildren(h("p", { class: "muted" }, `${a.audit.length} entries, newest first. Every change and every opening of the case is recorded with who did it.`),
      table(["when", "who", "what", "details"], auditRows(a.audit), "case-audit"));
  }, missing);
}

function caseView(id: number, body: HTMLElement, aliveFn: Alive, got: (c: CaseRecord) => void, missing: (e: unknown) => void,
                  onLeave: (f: () => void) => void): void {
  const img = h("img", { class: "render", alt: "Rendered view of the volume", "data-testid": "render-image", draggable: "false" });
  // A failed render says so on the picture itself, with the daemon's reason and a retry.
  const renderErrText = h("p", { class: "text" });
  const retry = h("button", { class: "btn", "data-testid": "render-retry" }, "Try again");
  const renderErr = h("div", { class: "render-error", role: "alert", "data-testid": "render-error", hidden: true },
    h("strong", {}, "The picture could not be made."), renderErrText, retry);
  const stage = h("div", { class: "render-stage", "data-testid": "render-stage" }, img, renderErr);
  const info = h("div", { class: "muted", "data-testid": "render-info" }, "Rendering…");
  let shownView: { view: View; size: { width: number; height: number } } | null = null;
  const presets = h("div", { class: "choices", "data-testid": "presets" });
  const views = h("div", { class: "choices two" });
  const opacityOut = h("span", { class: "value" }, "100 %");
  const opacity = h("input", { type: "range", min: 0, max: 100, step: 5, value: 100, class: "slider", "data-testid": "opacity" });
  const brainBtn = h("button", { class: "btn", "data-testid": "tf-brain-only" }, "Brain only");
  const tfTitle = h("span", { "data-testid": "tf-title" }, "");
  const v: View = { preset: "cortex_t1", opacity: 1, orbit: { azimuthDeg: 0, elevationDeg: 0, distanceMm: 450 }, tf: null, brainOnly: true };
  // The case's own volumes: its T1 (case_id on every request), its plan's CT/fMRI as layers.
  let layers: ModalityLayer[] = defaultLayers(["t1"]);
  let tabs: ModalityTabs | null = null;
  let hist: VolumeHistogram | null = null;
  const layerHist: Partial<Record<string, VolumeHistogram | null>> = {};  // ct / fmri, fetched when their tab is first shown
  let caseT1 = false;  // without a T1 of its own the case shows the daemon's MRI
  const tabsBox = h("div", { "data-testid": "modality-box" });
  const editor = new TfEditor((tf, final) => {
    if (tabs && tabs.selected.name !== "t1") {
      tabs.selected.tf = tf;
      tfTitle.textContent = ` (${MODALITY_LABEL[tabs.selected.name]}: custom, from ${tabs.selected.preset.replace(/_/g, " ")})`;
      if (final) want(false); else want(true);
      return;
    }
    v.tf = tf;
    mark(presets, "");
    tfTitle.textContent = ` (custom, from ${v.preset.replace(/_/g, " ")})`;
    timeline.push({ what: "change", t: performance.now(), size: "" });
    if (final) want(false); else want(true);
  });
  // Landmark picking on the model (writers, a case with a brain mask on the rendered grid).
  const pickBtn = h("button", { class: "btn", "data-testid": "pick-landmark", hidden: true }, "Pick landmark");
  const pickNote = h("p", { class: "muted", "data-testid": "pick-note", hidden: true });
  const pickMarks = h("div", { class: "pick-marks", "data-testid": "pick-marks" });
  let picking = false;
  let mask: NiftiVolume | null = null;
  let caseRec: CaseRecord | null = null;
  const side = h("aside", { class: "controls" },
    h("div", { class: "choices" }, pickBtn), pickNote,
    h("h2", {}, "Preset"), presets,
    tabsBox, h("h2", {}, "Transfer function", tfTitle), editor.el, h("div", { class: "choices" }, brainBtn),
    h("h2", {}, "Opacity ", opacityOut), opacity,
    h("h2", {}, "View"), views,
    h("p", { class: "muted" }, "Drag on the picture to turn the head; pinch with two fingers to zoom."), info);
  body.append(h("div", { class: "case-layout" }, stage, side));

  // The volume's geometry for the free orbit (GET /api/render/volume; 503 while it loads: the
  // named views are used meanwhile and the geometry is asked for again).
  let geo: VolumeGeometry | null = null;
  let geoTries = 0;
  const loadGeo = () => {
    const forCase = caseT1;  // an answer for the daemon's MRI that comes after the case's is dropped
    apiJson<VolumeGeometry>("GET", forCase ? `/api/render/volume?case_id=${id}` : "/api/render/volume").then((g) => {
      if (forCase !== caseT1) return;
      geo = g; stage.dataset.orbit = "free";
    }, () => {
      if (aliveFn() && forCase === caseT1 && ++geoTries < 30) setTimeout(loadGeo, 1000);
    });
  };
  loadGeo();
  const target = (view: View): Vec3 => (view.brainOnly && geo?.brain ? geo.brain.center_lps_mm : geo!.center_lps_mm);

  let url = "";
  const stream = `case-view-${Math.random().toString(36).slice(2, 10)}`;  // the daemon gives up our older full render for a newer view
  // The request of a view (POST /api/render; the pick sends the same fields, so it picks what is shown).
  const viewRequest = (view: View, size: { width: number; height: number }) => {
    const req: Record<string, unknown> = { width: size.width, height: size.height, opacity: view.opacity,
                                           focal_px: fitFocalPx(size.width, size.height, 450, 95) };
    if (view.tf) { req.tf = view.tf; req.brain_only = view.brainOnly; } else req.preset = view.preset;
    if (geo) req.T_camera_from_world = orbitPose(view.orbit, target(view));
    else { req.view = namedViewOf(view.orbit) ?? "left"; req.distance_mm = view.orbit.distanceMm; }
    return caseT1 ? Object.assign(req, caseRenderFields(id, layers, { preset: view.preset, tf: view.tf })) : req;
  };
  const sched = new RenderScheduler<View>({
    render: (view, size) => apiRender({ ...viewRequest(view, size), stream }),
    onImage: (r, _view, size, full) => {
      if (!aliveFn()) return;
      const ri = r as RenderedImage;
      if (url) URL.revokeObjectURL(url);
      url = URL.createObjectURL(ri.blob);
      img.dataset.seq = String(_view.seq ?? 0);
      img.src = url;
      renderErr.hidden = true;
      img.dataset.size = `${size.width}x${size.height}`;
      img.dataset.full = String(full);
      img.dataset.tf = _view.tf ? "custom" : _view.preset;
      shownView = { view: _view, size };
      info.textContent = `${ri.width}x${ri.height} ${full ? "" : "preview "}in ${ri.renderMs.toFixed(0)} ms (${ri.renderer})`;
      timeline.push({ what: full ? "full" : "preview", t: performance.now(), size: `${size.width}x${size.height}` });
    },
    onError: (e) => {
      if (!aliveFn()) return;
      if (tabs && /GL renderer/.test(plainMessage(e))) {  // a CPU-only daemon: the T1 alone
        layers = defaultLayers(["t1"]);
        tabs = null;
        tabsBox.replaceChildren(h("p", { class: "muted", "data-testid": "modality-note" }, "CT and fMRI layers need the GL renderer; the T1 is shown alone."));
        want(false);
        return;
      }
      showError(e);
      renderErrText.textContent = renderFailureNextStep(plainMessage(e), caseT1);
      renderErr.hidden = false;
      info.textContent = "No picture: the render failed.";
    },
    sizes: () => renderSizes(stage.clientWidth || 640, stage.clientHeight || 480, 1, { width: 1280, height: 1024 }),
    overtake: true,
    isSuperseded: (e) => e instanceof ApiError && e.code === "superseded",
  });
  onLeave(() => { if (url) URL.revokeObjectURL(url); });
  /** The view `v` changed: while a gesture goes on (`interactive`) a preview, else the picture. */
  // Buttons show a preview, then the full size; the same view asked for again (the tf point let
  // go where it was last dragged) makes nothing new unless forced (Try again).
  let lastWant = "";
  const want = (interactive: boolean, force = false) => {
    const key = JSON.stringify({ ...v, caseT1, layers });
    if (!interactive && !force && key === lastWant) return;
    lastWant = key;
    const view = { ...v, seq: ++viewSeq };
    if (interactive) sched.interactive(view); else sched.soon(view);
  };

  const mark = (box: HTMLElement, val: string) => box.querySelectorAll("button").forEach((b) => b.classList.toggle("active", b.dataset.value === val));
  const showOrbit = () => {
    mark(views, namedViewOf(v.orbit) ?? "");
    stage.dataset.azimuth = v.orbit.azimuthDeg.toFixed(1);
    stage.dataset.elevation = v.orbit.elevationDeg.toFixed(1);
    stage.dataset.distance = v.orbit.distanceMm.toFixed(0);
  };
  for (const name of ["left", "right", "anterior", "posterior", "superior", "inferior"])
    views.append(h("button", { class: "btn", "data-value": name, onclick: () => {
      v.orbit = { ...v.orbit, ...NAMED_VIEWS[name] };
      showOrbit();
      want(false);
    } }, name));
  showOrbit();
  const showBrain = () => {
    brainBtn.classList.toggle("active", v.brainOnly); brainBtn.textContent = v.brainOnly ? "Brain only: on" : "Brain only: off";
    const layer = tabs ? tabs.selected.name : "t1";
    const hl = layer === "t1" ? hist : layerHist[layer] ?? null;
    editor.setHistogram(hl ? histogramBars(hl, layer === "t1" && v.brainOnly) : null);  // only the T1 layer is masked
  };
  brainBtn.addEventListener("click", () => {
    if (!v.tf) { showError(new UserMessage("Brain only applies to an edited transfer function; the presets choose it themselves.")); return; }
    v.brainOnly = !v.brainOnly;
    showBrain();
    want(false);
  });
  showBrain();
  opacity.addEventListener("input", () => { v.opacity = Number(opacity.value) / 100; opacityOut.textContent = `${opacity.value} %`; want(true); });

  // Presets: each is also the starting point of the editor (its JSON from the daemon).
  let tfs: Record<string, TfJson> = {};
  const pickPreset = (p: string, render: boolean) => {
    v.preset = p;
    v.tf = null;
    v.brainOnly = BRAIN_PRESETS.has(p);
    mark(presets, p);
    tfTitle.textContent = ` (${p.replace(/_/g, " ")})`;
    if (tfs[p]) editor.load(tfs[p]);
    showBrain();
    if (render) want(false);
  };
  apiJson<{ presets: string[]; transfer_functions?: Record<string, TfJson> }>("GET", "/api/render/presets").then((r) => {
    tfs = r.transfer_functions ?? {};
    presets.replaceChildren(...r.presets.map((p) => h("button", { class: "btn", "data-value": p, onclick: () => pickPreset(p, true) }, p.replace(/_/g, " "))));
    if (!v.tf) pickPreset(v.preset, false);
  }, showError);
  retry.addEventListener("click", () => want(false, true));
  apiJson<CaseRecord>("GET", `/api/cases/${id}`).then((c) => {
    if (!aliveFn()) return;
    got(c);
    caseRec = c;
    pickBtn.hidden = !canWrite(session) || !(c.volumes ?? []).some((x) => x.modality === "mask");
    const t1 = newestT1(c);
    caseT1 = t1 !== null;
    if (caseT1) { geo = null; geoTries = 0; loadGeo(); }
    if (t1 !== null) apiJson<VolumeHistogram>("GET", histogramPath(id, t1)).then((r) => { hist = r; showBrain(); }, () => undefined);
    if (planModalities(c).length > 1) {
      layers = defaultLayers(planModalities(c));
      tabs = new ModalityTabs(layers, (l) => {
        // The editor's title names the tab's function (it said the T1's on every tab).
        if (l.name === "t1") {
          if (v.tf) editor.load(v.tf); else if (tfs[v.preset]) editor.load(tfs[v.preset]);
          tfTitle.textContent = v.tf ? ` (custom, from ${v.preset.replace(/_/g, " ")})` : ` (${v.preset.replace(/_/g, " ")})`;
        } else {
          const t = l.tf ?? tfs[l.preset]; if (t) editor.load(t);
          tfTitle.textContent = ` (${MODALITY_LABEL[l.name]}: ${l.tf ? "custom, from " : ""}${l.preset.replace(/_/g, " ")})`;
        }
        const path = layerHistogramPath(id, l.name, null);
        if (l.name !== "t1" && path && !(l.name in layerHist)) {
          layerHist[l.name] = null;
          apiJson<VolumeHistogram>("GET", path).then((r) => { layerHist[l.name] = r; showBrain(); }, () => undefined);
        }
        showBrain();
      }, (final) => (final ? want(false) : want(true)));
      tabsBox.replaceChildren(h("h2", {}, "Modalities"), tabs.el);
    }
    want(false);
  }, missing);
  stage.append(pickMarks);

  // The camera of the picture shown: its pose and intrinsics (as the daemon made it).
  const shownCamera = () => {
    if (!shownView || !geo) return null;
    const { view, size } = shownView;
    const f = fitFocalPx(size.width, size.height, 450, 95);
    return { T: orbitPose(view.orbit, target(view)), K: { fx: f, fy: f, cx: (size.width - 1) / 2, cy: (size.height - 1) / 2 }, size };
  };
  // Screen <-> picture pixel (the image is shown contained in the stage).
  const imgBox = (size: { width: number; height: number }) => {
    const r = stage.getBoundingClientRect();
    const k = Math.min(r.width / size.width, r.height / size.height);
    return { k, x0: r.left + (r.width - size.width * k) / 2, y0: r.top + (r.height - size.height * k) / 2, r };
  };
  const drawPickMarks = () => {
    pickMarks.replaceChildren();
    const cam = shownCamera();
    if (!picking || !cam) return;
    const b = imgBox(cam.size);
    const pts: [string, number[], string][] = [
      ...(caseRec?.landmarks?.points ?? []).map((p, i) => [String(i + 1), p.world_mm, "lm"] as [string, number[], string]),
      ...(pendingModelPoints.get(id) ?? []).map((p) => ["+", p, "pending"] as [string, number[], string]),
    ];
    for (const [label, w, cls] of pts) {
      const px = projectPoint(cam.T, cam.K, w);
      if (!px) continue;
      const dot = h("span", { class: `pick-dot ${cls}`, "data-testid": `pick-dot-${cls}` }, label);
      dot.style.left = `${b.x0 - b.r.left + (px[0] + 0.5) * b.k}px`;
      dot.style.top = `${b.y0 - b.r.top + (px[1] + 0.5) * b.k}px`;
      pickMarks.append(dot);
    }
  };
  new ResizeObserver(() => drawPickMarks()).observe(stage);
  img.addEventListener("load", () => drawPickMarks());
  pickBtn.addEventListener("click", async () => {
    if (picking) { picking = false; pickBtn.classList.remove("active"); pickNote.hidden = true; drawPickMarks(); return; }
    try {
      if (!geo) throw new UserMessage("The volume's geometry is not known yet (the MRI is still loading); try again in a moment.");
      if (!mask) {
        const mv = [...(caseRec?.volumes ?? [])].filter((x) => x.modality === "mask").sort((a, b) => b.id - a.id)[0];
        if (!mv) throw new UserMessage("This case has no brain mask to pick on; upload one (modality mask) in Contents.");
        pickNote.hidden = false;
        pickNote.textContent = `Loading the brain mask (${fmtBytes(mv.size_bytes)})…`;
        // Read in a Web Worker (off_thread.ts): on this thread a 256^3 mask froze the page (7.34).
        const m = await parseNiftiOffThread(await (await apiBlob(`/api/cases/${id}/volumes/${mv.id}`)).arrayBuffer(), mv.original_name);
        // The picture is the daemon's MRI: picking on this case's mask is right only on the same grid.
        const c = centreLps(m);
        const same = geo.dims?.every((d, i) => d === m.dims[i]) !== false &&
                     Math.hypot(c[0] - geo.center_lps_mm[0], c[1] - geo.center_lps_mm[1], c[2] - geo.center_lps_mm[2]) < 1;
        if (!same) throw new UserMessage(`The 3D view shows the daemon's MRI, not this case's volume (${mv.original_name} has another grid); a point picked here would be in the wrong place.`);
        mask = m;
      }
      picking = true;
      pickBtn.classList.add("active");
      pickNote.hidden = false;
      pickNote.textContent = "Tap the model where the landmark is; then tap its twin on the photo (Photo & marks).";
      drawPickMarks();
    } catch (e) { pickNote.hidden = true; showError(e); }
  });
  // The daemon picks on the rendering itself (POST /api/render/pick: the renderer's depth at that
  // pixel of the very view shown), so the point lands on the surface the transfer function shows.
  const pickAt = async (x: number, y: number) => {
    const cam = shownCamera();
    if (!cam || !mask || !shownView) return;
    const b = imgBox(cam.size);
    const u = (x - b.x0) / b.k - 0.5, w = (y - b.y0) / b.k - 0.5;
    if (u < -0.5 || w < -0.5 || u >= cam.size.width - 0.5 || w >= cam.size.height - 0.5) return;
    let hit: Vec3;
    try {
      const r = await apiJson<{ p_world_mm: Vec3 }>("POST", "/api/render/pick", { ...viewRequest(shownView.view, shownView.size), pixel: [u, w] });
      hit = r.p_world_mm;
    } catch (e) {
      if (e instanceof ApiError && e.status === 422) showError(new UserMessage("That tap missed the brain: tap on the model itself."));
      else showError(e);
      return;
    }
    if (!aliveFn()) return;
    pendingModelPoints.set(id, [...(pendingModelPoints.get(id) ?? []), hit]);
    stage.dataset.picked = String(pendingModelPoints.get(id)!.length);
    showNotice(`Model point picked at (${hit.map((q) => q.toFixed(1)).join(", ")}) mm. Now tap its twin on the photo (Photo & marks).`);
    drawPickMarks();
  };

  // Touch: one finger orbits about the volume's centre (0.4 degrees a pixel), two fingers pinch
  // to zoom (the distance); a wheel zooms too.
  const fingers = new Map<number, { x: number; y: number }>();
  let gesture: { orbit: Orbit; x: number; y: number; spread: number } | null = null;
  const spread = () => { const [a, b] = [...fingers.values()]; return a && b ? Math.hypot(a.x - b.x, a.y - b.y) : 0; };
  const begin = () => {
    const [a] = [...fingers.values()];
    gesture = a ? { orbit: { ...v.orbit }, x: a.x, y: a.y, spread: spread() } : null;
  };
  const changed = () => { showOrbit(); timeline.push({ what: "change", t: performance.now(), size: "" }); want(true); };
  let tap: { id: number; x: number; y: number; moved: boolean } | null = null;
  stage.addEventListener("pointerdown", (e) => {
    if (e.target instanceof HTMLButtonElement) return;
    tap = fingers.size === 0 ? { id: e.pointerId, x: e.clientX, y: e.clientY, moved: false } : null;
    fingers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    stage.setPointerCapture(e.pointerId);
    begin();
  });
  stage.addEventListener("pointermove", (e) => {
    if (tap && e.pointerId === tap.id && Math.hypot(e.clientX - tap.x, e.clientY - tap.y) > 8) tap.moved = true;
    if (picking && tap && !tap.moved && fingers.size === 1) return; // a tap in pick mode does not turn the head
    if (!fingers.has(e.pointerId) || !gesture) return;
    fingers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    if (fingers.size >= 2 && gesture.spread > 10) v.orbit = zoomOrbit(gesture.orbit, spread() / gesture.spread);
    else if (fingers.size === 1) {
      const [a] = [...fingers.values()];
      v.orbit = dragOrbit(gesture.orbit, a.x - gesture.x, a.y - gesture.y);
    } else return;
    changed();
  });
  const end = (e: PointerEvent) => {
    if (picking && tap && e.pointerId === tap.id && !tap.moved && e.type === "pointerup") pickAt(e.clientX, e.clientY);
    if (tap && e.pointerId === tap.id) tap = null;
    fingers.delete(e.pointerId);
    begin();
  };
  stage.addEventListener("pointerup", end);
  stage.addEventListener("pointercancel", end);
  stage.addEventListener("wheel", (e) => { e.preventDefault(); v.orbit = zoomOrbit(v.orbit, Math.exp(-e.deltaY / 500)); changed(); }, { passive: false });
}

// ---- Jobs --------------------------------------------------------------------------------
function jobsScreen(): void {
  const folder = h("select", { class: "field grow", "data-testid": "case-folder" });
  const startBtn = h("button", { class: "btn primary", "data-testid": "start-register" }, "Start registration");
  const list = h("div", { class: "list", "data-testid": "job-list" });
  const canvas = h("canvas", { class: "plot", width: 480, height: 200, "data-testid": "nmi-plot" });
  const plotTitle = h("h2", {}, "NMI against evaluations");
  let selected: number | null = null;
  const writer = canWrite(session);
  main.append(h("h1", {}, "Jobs"),
    writer ? h("div", { class: "toolbar", "data-write": "" }, h("label", { class: "muted" }, "Phantom case"), folder, startBtn)
           : h("p", { class: "muted" }, "Read-only: jobs are shown, not started or cancelled."),
    h("div", { class: "jobs-layout" }, list, h("div", { class: "plot-box" }, plotTitle, canvas)));

  if (writer) apiJson<{ folders: string[] }>("GET", "/api/case-folders").then((r) => {
    folder.replaceChildren(...r.folders.map((f) => h("option", { value: f }, f)));
    if (!r.folders.length) folder.append(h("option", { value: "" }, "No case folders yet"));
  }, showError);

  startBtn.addEventListener("click", async () => {
    if (!folder.value) { showError(new UserMessage("No phantom case folder to register yet; the daemon makes one at start.")); return; }
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
      el: h("div", { class: "job", "data-testid": "job-card", "data-job-id": j.id, "data-case-id": String(j.params?.case_id ?? ""),
                     onclick: () => { selected = j.id; render(); } }),
      badge: h("span", { class: "badge" }), bar: h("div", { class: "bar" }), stage: h("span"), nmi: h("span"),
      evals: h("span"), error: h("div", { class: "job-error" }),
      cancel: h("button", { class: "btn danger", "data-testid": "cancel-job", "data-write": "" }, "Cancel"),
    };
    c.cancel.addEventListener("click", async (ev) => {
      ev.stopPropagation();
      c.cancel.disabled = true;
      try { upsertJob(await apiJson<Job>("POST", `/api/jobs/${j.id}/cancel`)); } catch (e) { c.cancel.disabled = false; showError(e); }
    });
    c.el.append(
      h("div", { class: "job-head" }, h("strong", {}, `#${j.id} ${j.kind}`), c.badge,
        h("span", { class: "muted grow" }, j.params?.case_id !== undefined ? `case #${j.params.case_id} of the store` : String(j.params?.case ?? ""))),
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
      c.cancel.hidden = !active || !writer;
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

// Start: the stored session (this tab) if any, then ask the daemon whether it lets us in.
session = loadSession(sessionStorage) ?? KIOSK;
applySession();
pollStatus();
probeAccess();
