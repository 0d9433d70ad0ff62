// The Tracker screen of a case (issue 7): tools seen or missing, the measured rate and each
// tool's RMS error, the pointer tip live on three orthogonal MRI slices, and the patient
// registration by touching the fiducials with the pointer (docs/ui.md "Tracker",
// docs/api/navigation.md). Logic in tracker_model.ts.
import "./tracker_screen.css";
import { apiBlob, apiJson, plainMessage } from "./api";
import { h } from "./dom";
import { landmarksPanel } from "./landmarks_panel";
import {
  canRegister, fiducialLines, fmtPoint, freVerdict, needsNewSlices, newFiducialLabel, nextFiducial, pivotLine, placeFiducial, pointerInImage, rateView,
  caseSliceVolume, sliceCaptionText, sliceTapToImageMm, slicesPath, suggestedFiducialsPath, tipLine, toolViews,
  type NavState, type PivotAnswer, type PointerAnswer, type Registration, type SliceVolume, type Vec3,
} from "./tracker_model";

export interface TrackerScreenDeps {
  alive: () => boolean;
  writable: boolean; // false for reviewers: everything shown, nothing changed
  showError: (e: unknown) => void;
  showNotice: (text: string) => void;
  onLeave: (f: () => void) => void;
}

const POLL_MS = 100;
const SLICE_PX = 240;

export function trackerScreen(caseId: number, body: HTMLElement, deps: TrackerScreenDeps): void {
  const base = `/api/cases/${caseId}/navigation`;
  let nav: NavState | null = null;
  let reg: Registration | null = null; // computed from the current fiducials (not yet accepted)
  let regError = "";
  let selected: string | null = null;
  let pointer: PointerAnswer | null = null;
  let isSim = false;
  let busy = false;
  // The slices' volume: the case's own T1 once its record says it has one, else data.t1;
  // undefined until the record is read (no slices asked for before, so none of the wrong head).
  let sliceVol: SliceVolume | null | undefined;

  // ---- left: tools and the live view ----
  const tools = h("ul", { class: "nav-tools", "data-testid": "tracker-tools" });
  const rate = h("span", { class: "pill", "data-testid": "tracker-rate" }, "—");
  const sliceImg = h("img", { class: "nav-slices", alt: "Axial, coronal and sagittal MRI slices at the pointer tip", "data-testid": "tracker-slices" });
  const sliceCaption = h("p", { class: "muted nav-caption", "data-testid": "tracker-slice-caption" }, "Waiting for the tracker…");
  const tipText = h("p", { class: "muted", "data-testid": "tip-line" }, "");
  const pivot = h("button", { class: "btn", type: "button", "data-testid": "pivot-btn", hidden: !deps.writable }, "Calibrate tip (pivot, 5 s)");
  const placeFid = h("button", { class: "btn", type: "button", "data-testid": "place-fid-btn", hidden: !deps.writable }, "Place fiducial on the MRI");
  const left = h("section", { class: "panel nav-live" },
    h("div", { class: "nav-row" }, h("h2", {}, "Tools"), rate), tools,
    h("div", { class: "nav-row" }, h("span", { class: "grow" }, tipText), pivot),
    h("div", { class: "nav-slice-labels" }, h("span", {}, "Axial"), h("span", {}, "Coronal"), h("span", {}, "Sagittal")),
    sliceImg, sliceCaption, h("div", { class: "nav-row" }, placeFid));

  // ---- right: patient registration ----
  const list = h("div", { class: "nav-fids", "data-testid": "fid-list" });
  const msg = h("p", { class: "nav-msg", role: "alert", "data-testid": "nav-msg", hidden: true });
  const record = h("button", { class: "btn primary nav-record", type: "button", "data-testid": "record-btn" }, "Record");
  const simTouch = h("button", { class: "btn", type: "button", "data-testid": "sim-touch-btn", hidden: true }, "Simulator: touch it");
  const suggest = h("button", { class: "btn", type: "button", "data-testid": "suggest-btn", hidden: true }, "Use suggested skin fiducials");
  const fre = h("p", { class: "nav-fre", "data-testid": "fre-line" }, "");
  const accept = h("button", { class: "btn primary", type: "button", "data-testid": "accept-btn" }, "Accept registration");
  const redo = h("button", { class: "btn danger", type: "button", "data-testid": "redo-btn" }, "Redo: clear recorded");
  const accepted = h("p", { class: "muted", "data-testid": "accepted-line" }, "");
  const readOnly = h("p", { class: "muted", hidden: deps.writable }, "Read-only: reviewers see the registration but cannot record or accept.");
  const right = h("section", { class: "panel nav-reg" },
    h("h2", {}, "Patient registration"), readOnly, suggest,
    h("p", { class: "muted" }, "Touch each fiducial with the pointer tip, hold still, press Record."),
    record, h("div", { class: "nav-row" }, simTouch), msg, fre,
    h("div", { class: "nav-row" }, accept, redo), accepted, list);
  // ---- below: cortical landmarks and brain shift (landmarks_panel.ts) ----
  const landmarks = landmarksPanel(caseId, { alive: deps.alive, writable: deps.writable, hasAccepted: () => !!nav?.accepted });
  body.replaceChildren(h("div", { class: "nav-screen", "data-testid": "tracker-screen" }, left, right, landmarks.el));

  const say = (text: string, bad = true) => {
    msg.textContent = text;
    msg.className = `nav-msg ${bad ? "bad" : "ok"}`;
    msg.hidden = !text;
  };

  // ---- registration panel ----
  function draw(): void {
    if (!nav) return;
    const next = nextFiducial(nav, selected);
    const lines = fiducialLines(nav, reg);
    list.replaceChildren(...lines.map((l) =>
      h("button", {
        class: `nav-fid ${l.level}${l.label === next ? " next" : ""}`, type: "button", "data-testid": `fid-row-${l.label}`,
        "data-recorded": l.recorded ? "true" : "false", click: () => { selected = l.label; draw(); },
      },
      h("span", { class: "nav-fid-label" }, l.label), h("span", { class: "nav-fid-res" }, l.residual), h("span", { class: "nav-fid-note" }, l.note))));
    if (!nav.image_fiducials.fiducials.length) list.append(h("p", { class: "muted" }, "No fiducials on the MRI yet."));
    suggest.hidden = !deps.writable || nav.image_fiducials.fiducials.length > 0;
    record.textContent = next ? `Record “${next}”` : "All recorded";
    record.disabled = !deps.writable || !next || busy;
    simTouch.hidden = !isSim || !deps.writable || !next;
    simTouch.textContent = next ? `Simulator: touch “${next}”` : "Simulator";
    if (reg) {
      const v = freVerdict(reg.fre_mm);
      fre.textContent = `${v.text}; ${reg.n_used} used${reg.excluded.length ? `, excluded: ${reg.excluded.join(", ")}` : ""}; predicted TRE ${reg.predicted_tre_mm.toFixed(2)} mm (${reg.target})`;
      fre.className = `nav-fre ${v.level}`;
      fre.dataset.fre = String(reg.fre_mm);
    } else {
      fre.textContent = regError || (canRegister(nav) ? "" : "Record at least 3 fiducials to see the FRE.");
      fre.className = `nav-fre${regError ? " bad" : ""}`;
      delete fre.dataset.fre;
    }
    const sameAsAccepted = !!reg && !!nav.accepted && nav.accepted.image_fiducials_revision === reg.image_fiducials_revision &&
      nav.accepted.patient_fiducials_revision === reg.patient_fiducials_revision;
    accept.disabled = !deps.writable || !reg || busy || sameAsAccepted;
    accept.textContent = sameAsAccepted ? "Accepted" : "Accept registration";
    redo.disabled = !deps.writable || !nav.patient_fiducials.fiducials.length || busy;
    const a = nav.accepted;
    accepted.textContent = a
      ? `Accepted: FRE ${a.fre_mm.toFixed(2)} mm, ${a.n_used} fiducials, ${a.accepted_utc ?? ""} (revision ${a.revision}; ${nav.accepted_count} accepted in all). The pointer is shown on the MRI through it.`
      : "No registration accepted yet.";
    accepted.dataset.revision = a?.revision ? String(a.revision) : "";
  }

  async function reload(): Promise<void> {
    nav = await apiJson<NavState>("GET", base);
    reg = null;
    regError = "";
    if (canRegister(nav)) {
      try {
        reg = await apiJson<Registration>("POST", `${base}/register`, {});
      } catch (e) {
        regError = plainMessage(e);
      }
    }
    if (deps.alive()) draw();
    await landmarks.refresh();
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

  record.addEventListener("click", () => act(async () => {
    const label = nav && nextFiducial(nav, selected);
    if (!label) return;
    const r = await apiJson<{ recorded: { spread_mm: number; frames: number } }>("POST", `${base}/record`, { label });
    selected = null;
    say(`Recorded “${label}” (${r.recorded.frames} frames, tip still within ${r.recorded.spread_mm.toFixed(2)} mm).`, false);
    await reload();
  }));
  simTouch.addEventListener("click", () => act(async () => {
    const label = nav && nextFiducial(nav, selected);
    const f = nav?.image_fiducials.fiducials.find((x) => x.label === label);
    if (!f) return;
    await apiJson("POST", "/api/tracker/sim/pointer", { touch_image_mm: f.p_image_mm });
    say(`The simulated pointer rests on “${f.label}”: press Record.`, false);
  }));
  suggest.addEventListener("click", () => act(async () => {
    const s = await apiJson<{ fiducials: { label: string; p_image_mm: Vec3 }[] }>("GET", suggestedFiducialsPath(sliceVol ?? null));
    await apiJson("POST", `${base}/image-fiducials`, { fiducials: s.fiducials });
    say(`${s.fiducials.length} skin fiducials placed on the MRI.`, false);
    await reload();
  }));
  accept.addEventListener("click", () => act(async () => {
    if (!reg) return;
    const a = await apiJson<Registration & { state: string }>("POST", `${base}/accept`, {
      image_fiducials_revision: reg.image_fiducials_revision, patient_fiducials_revision: reg.patient_fiducials_revision,
      outlier_mm: reg.params.outlier_mm, fle_mm: reg.params.fle_mm,
    });
    deps.showNotice(`Patient registration accepted: FRE ${a.fre_mm.toFixed(2)} mm.`);
    say("");
    await reload();
  }));
  pivot.addEventListener("click", () => act(async () => {
    pivot.textContent = "Pivoting: tip in the divot, swivel the handle…";
    try {
      const p = await apiJson<PivotAnswer>("POST", "/api/navigation/pivot", { seconds: 5, apply: true });
      say(pivotLine(p), false);
    } finally {
      pivot.textContent = "Calibrate tip (pivot, 5 s)";
    }
  }));
  // Image fiducials by touch on the slices: with "Place fiducial" on, a tap puts the selected
  // fiducial (or a new one, F<n>) at the point the tapped slice shows there.
  let placing = false;
  const showPlacing = () => {
    placeFid.classList.toggle("active", placing);
    placeFid.textContent = placing ? `Tap the slices: ${selected ? `move “${selected}”` : "a new fiducial"}` : "Place fiducial on the MRI";
    sliceImg.classList.toggle("placing", placing);
  };
  placeFid.addEventListener("click", () => { placing = !placing; showPlacing(); });
  list.addEventListener("click", () => { if (placing) showPlacing(); });
  sliceImg.addEventListener("click", (e) => {
    if (!placing || !nav || !sliceImg.dataset.point) return;
    const r = sliceImg.getBoundingClientRect();
    const centre = sliceImg.dataset.point.split(",").map(Number) as Vec3;
    const p = sliceTapToImageMm(centre, ((e.clientX - r.left) / r.width) * 3 * SLICE_PX, ((e.clientY - r.top) / r.height) * SLICE_PX, SLICE_PX);
    if (!p) return;
    const fids = nav.image_fiducials.fiducials;
    const label = selected && fids.some((f) => f.label === selected) ? selected : newFiducialLabel(fids);
    void act(async () => {
      await apiJson("POST", `${base}/image-fiducials`, { fiducials: placeFiducial(fids, label, p) });
      selected = label;
      say(`Fiducial “${label}” placed on the MRI at ${fmtPoint(p)}.`, false);
      await reload();
      showPlacing();
    });
  });
  redo.addEventListener("click", () => act(async () => {
    await apiJson("DELETE", `${base}/patient-fiducials`);
    selected = null;
    say("Recorded fiducials cleared: touch them again.", false);
    await reload();
  }));

  // ---- live: tools and the slices ----
  let lastP: Vec3 | null = null;
  let sliceInFlight = false;
  let sliceUrl = "";
  let sliceError = "";  // the last slice request's failure, said under the picture until one succeeds
  let sliceRetryAt = 0;
  const drawLive = () => {
    const views = toolViews(pointer);
    tools.replaceChildren(...views.map((v) =>
      h("li", { class: `nav-tool ${v.level}`, "data-testid": `tool-${v.name}`, "data-level": v.level },
        h("span", { class: "nav-dot", "aria-hidden": "true" }), h("strong", {}, v.name), h("span", {}, v.text), h("span", { class: "muted" }, `RMS ${v.rms}`))));
    tipText.textContent = tipLine(pointer);
    pivot.disabled = busy;
    const rv = rateView(pointer);
    rate.textContent = rv.text;
    rate.className = `pill ${rv.level}`;
    // What the slices show: the tip through the accepted registration (else the one computed
    // now, as a preview), else the fiducial to touch next.
    const through = nav?.accepted ?? reg;
    let p = pointerInImage(pointer, through);
    let caption = p ? `Pointer tip ${fmtPoint(p)} (${nav?.accepted ? "accepted registration" : "preview: not accepted"})` : "";
    if (!p && nav) {
      const label = nextFiducial(nav, selected);
      const f = nav.image_fiducials.fiducials.find((x) => x.label === label);
      if (f) {
        p = f.p_image_mm;
        caption = `Fiducial “${f.label}” on the MRI ${fmtPoint(p)}: touch it on the patient`;
      } else caption = pointer?.p_reference_mm ? "No registration yet: the pointer cannot be placed on the MRI." : "Pointer or reference not seen.";
    }
    sliceCaption.textContent = sliceCaptionText(caption, sliceError);
    if (sliceVol !== undefined && !sliceInFlight && needsNewSlices(lastP, p) && performance.now() >= sliceRetryAt) {
      sliceInFlight = true;
      const at = p as Vec3;
      const vol = sliceVol;
      apiBlob(slicesPath(at, SLICE_PX, undefined, vol)).then((b) => {
        if (!deps.alive()) return;
        if (sliceUrl) URL.revokeObjectURL(sliceUrl);
        sliceUrl = URL.createObjectURL(b);
        sliceImg.src = sliceUrl;
        sliceImg.dataset.point = at.map((v) => v.toFixed(1)).join(",");
        sliceImg.dataset.volume = vol ? `case ${vol.caseId} volume ${vol.volumeId}` : "bundled";
        lastP = at;
        sliceError = "";
        delete sliceImg.dataset.error;
      }).catch((e) => {
        // Said under the picture (and on it: data-error); asked again a second later.
        sliceError = plainMessage(e);
        sliceImg.dataset.error = sliceError;
        sliceRetryAt = performance.now() + 1000;
        if (deps.alive()) sliceCaption.textContent = sliceCaptionText(caption, sliceError);
      })
        .finally(() => { sliceInFlight = false; });
    }
  };
  const poll = async () => {
    while (deps.alive()) {
      try {
        pointer = await apiJson<PointerAnswer>("GET", "/api/navigation/pointer");
      } catch {
        pointer = null;
      }
      if (!deps.alive()) break;
      drawLive();
      await new Promise((r) => setTimeout(r, POLL_MS));
    }
  };
  deps.onLeave(() => { if (sliceUrl) URL.revokeObjectURL(sliceUrl); });

  apiJson<{ modules?: { tracker?: { source?: string } } }>("GET", "/api/status")
    .then((s) => { isSim = s.modules?.tracker?.source === "sim"; draw(); }).catch(() => {});
  // The case's own T1 for the slices (and the suggested fiducials); the bundled MRI without one
  // or when the record cannot be read.
  apiJson<{ id: number; volumes?: { id: number; modality: string }[] }>("GET", `/api/cases/${caseId}`)
    .then((c) => { sliceVol = caseSliceVolume(c); }, () => { sliceVol = null; })
    .finally(() => { suggest.dataset.volume = sliceVol ? `case ${sliceVol.caseId} volume ${sliceVol.volumeId}` : "bundled"; });
  reload().catch((e) => { deps.showError(e); say(plainMessage(e)); });
  poll();
}
