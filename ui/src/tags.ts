// Stimulation tags in the fused view (issue 7; docs/api/tags.md): the surgeon taps the photo (the
// fused view at the registered camera shows it pixel for pixel), the daemon casts each tag's photo
// pixel onto the plan's brain surface with the registration's pose, and the tags are drawn as
// markers projected with the view's own pose, so they stay on the brain when the view turns.
//
// Coordinates: photo and view pixels are OpenCV's (the centre of the top-left pixel at (0, 0));
// the overlay's SVG user units are view pixels with their edges at integers (x_svg = x_px + 0.5).
// The view is the photo's camera resized to the view's size (core's Intrinsics::resized), as the
// daemon renders it. Markers ignore lens distortion (a pinhole projection; the phantom and most
// calibrated cameras here have under a pixel of it at the marks' scale).
import { apiJson } from "./api";
import { h } from "./dom";
import "./tags.css";

export type Mat4 = number[][];
export interface Intrinsics { width: number; height: number; fx: number; fy: number; cx: number; cy: number }

/** A tag as the daemon answers it (world_mm and normal_world are its cast onto the surface). */
export interface Tag {
  label: string;
  colour: string; // "#rrggbb"
  note: string;
  pixel: [number, number]; // photo pixel (OpenCV)
  world_mm?: [number, number, number]; // LPS mm, the case's T1
  normal_world?: [number, number, number];
}
export interface TagSet { revision: number; registration_id: number | null; tags: Tag[]; id?: number; created_utc?: string }

/** Eight colours that read on the dark theme and on a photo of cortex (red is the usual one). */
export const TAG_COLOURS = ["#ff4040", "#ffb020", "#ffe060", "#40d070", "#30c0ff", "#4060ff", "#d060ff", "#ffffff"];

/** The first free label S1, S2, ... */
export function nextLabel(tags: Tag[]): string {
  const used = new Set(tags.map((t) => t.label));
  for (let i = 1; ; i++) if (!used.has(`S${i}`)) return `S${i}`;
}

/** A view pixel (OpenCV) -> the photo pixel it shows at the registered camera (the view is the photo resized). */
export function viewToPhotoPixel(xView: number, yView: number, K: Intrinsics, viewW: number, viewH: number): [number, number] {
  return [(xView + 0.5) * (K.width / viewW) - 0.5, (yView + 0.5) * (K.height / viewH) - 0.5];
}

/** The world point (LPS mm) in the view of pose T (T_camera_from_world) with the photo's camera
 *  resized to viewW x viewH: the view pixel, its depth and whether the surface faces the camera;
 *  null behind the camera. */
export function projectToView(T: Mat4, K: Intrinsics, viewW: number, viewH: number, p: number[], n?: number[]):
    { x: number; y: number; depthMm: number; facing: boolean } | null {
  const c = [0, 1, 2].map((i) => T[i][0] * p[0] + T[i][1] * p[1] + T[i][2] * p[2] + T[i][3]);
  if (!(c[2] > 1e-6)) return null;
  const sx = viewW / K.width, sy = viewH / K.height;
  const fx = K.fx * sx, fy = K.fy * sy, cx = (K.cx + 0.5) * sx - 0.5, cy = (K.cy + 0.5) * sy - 0.5;
  let facing = true;
  if (n) {
    const nc = [0, 1, 2].map((i) => T[i][0] * n[0] + T[i][1] * n[1] + T[i][2] * n[2]);
    facing = nc[0] * c[0] + nc[1] * c[1] + nc[2] * c[2] < 0; // the outward normal points back at the camera
  }
  return { x: fx * (c[0] / c[2]) + cx, y: fy * (c[1] / c[2]) + cy, depthMm: c[2], facing };
}

/** The request body of POST /api/cases/N/tags (the daemon recomputes the cast; only the marks go). */
export function tagsBody(tags: Tag[], registrationId?: number): { tags: { label: string; colour: string; note: string; pixel: [number, number] }[]; registration_id?: number } {
  const b: ReturnType<typeof tagsBody> = { tags: tags.map((t) => ({ label: t.label, colour: t.colour, note: t.note, pixel: [t.pixel[0], t.pixel[1]] })) };
  if (registrationId !== undefined) b.registration_id = registrationId;
  return b;
}

/** Index of the tag whose marker (view pixel `at`) is nearest to `p` within `radius`, or -1. */
export function nearestMarker(at: ({ x: number; y: number } | null)[], p: { x: number; y: number }, radius: number): number {
  let best = -1, bd = radius;
  at.forEach((q, i) => {
    if (!q) return;
    const d = Math.hypot(q.x - p.x, q.y - p.y);
    if (d <= bd) { bd = d; best = i; }
  });
  return best;
}

export interface TagsOptions {
  caseId: number;
  registrationId: number;
  stage: HTMLElement; // the fused picture's stage (position: relative)
  panel: HTMLElement; // where the controls go
  K: Intrinsics; // the photo's camera
  viewW: number;
  viewH: number;
  pose: () => Mat4; // the view's T_camera_from_world now
  atCamera: () => boolean; // the view is the registered camera (taps are photo pixels)
  toCamera: () => Promise<void>; // snap the view back to it
  canWrite: boolean;
  showError: (e: unknown) => void;
}

/** The tags' overlay and panel in the fused view. `redraw()` after every new picture. */
export function mountTags(o: TagsOptions): { redraw: () => void; placing: () => boolean } {
  const NS = "http://www.w3.org/2000/svg";
  const svg = document.createElementNS(NS, "svg");
  svg.setAttribute("viewBox", `0 0 ${o.viewW} ${o.viewH}`);
  svg.setAttribute("class", "tags-overlay");
  svg.setAttribute("data-testid", "tags-overlay");
  o.stage.append(svg);
  let tags: Tag[] = [];
  let colour = TAG_COLOURS[0];
  let placing = false, busy = false;
  const status = h("p", { class: "muted", "data-testid": "tags-status" }, "Loading tags…");
  const list = h("div", { class: "tag-list", "data-testid": "tag-list" });
  const note = h("input", { type: "text", class: "field", placeholder: "Note for the next tag (e.g. hand motor)", maxlength: 200, "data-testid": "tag-note" });
  const placeBtn = h("button", { class: "btn big", "data-testid": "tag-place", "data-write": "" }, "Place tag");
  const swatches = h("div", { class: "swatches", "data-write": "" }, ...TAG_COLOURS.map((c) =>
    h("button", { class: "swatch", style: `background:${c}`, "data-colour": c, "aria-label": `colour ${c}`, onclick: () => { colour = c; paintSwatches(); } })));
  const paintSwatches = () => swatches.querySelectorAll<HTMLButtonElement>("button").forEach((b) => b.classList.toggle("active", b.dataset.colour === colour));
  paintSwatches();
  o.panel.append(h("h2", {}, "Stimulation tags"), ...(o.canWrite ? [placeBtn, swatches, note] : []), status, list);

  const scale = () => {
    const r = o.stage.getBoundingClientRect();
    return Math.min(r.width / o.viewW, r.height / o.viewH) || 1;
  };
  const shown = (): ({ x: number; y: number; facing: boolean } | null)[] =>
    tags.map((t) => (t.world_mm ? projectToView(o.pose(), o.K, o.viewW, o.viewH, t.world_mm, t.normal_world) : null));
  const redraw = () => {
    svg.replaceChildren();
    const r = 12 / scale(); // 24 CSS px markers
    shown().forEach((q, i) => {
      if (!q) return;
      const t = tags[i];
      const g = document.createElementNS(NS, "g");
      g.setAttribute("data-testid", "tag-marker");
      g.setAttribute("data-label", t.label);
      g.setAttribute("data-x", q.x.toFixed(2));
      g.setAttribute("data-y", q.y.toFixed(2));
      const c = document.createElementNS(NS, "circle");
      c.setAttribute("cx", String(q.x + 0.5));
      c.setAttribute("cy", String(q.y + 0.5));
      c.setAttribute("r", String(r));
      c.setAttribute("class", q.facing ? "tag-dot" : "tag-dot behind");
      c.setAttribute("style", `stroke:${t.colour};fill:${q.facing ? t.colour + "99" : "none"}`);
      const l = document.createElementNS(NS, "text");
      l.setAttribute("x", String(q.x + 0.5 + 1.3 * r));
      l.setAttribute("y", String(q.y + 0.5 + 0.45 * r));
      l.setAttribute("font-size", String(1.2 * r));
      l.setAttribute("class", "tag-label");
      l.textContent = t.label;
      g.append(c, l);
      svg.append(g);
    });
  };
  const fmt = (v: number[] | undefined) => (v ? v.map((x) => x.toFixed(1)).join(", ") : "–");
  const paintList = () => {
    list.replaceChildren(...tags.map((t, i) => h("div", { class: "tag-row", "data-testid": "tag-row" },
      h("span", { class: "tag-swatch", style: `background:${t.colour}` }),
      h("span", { class: "tag-text" }, h("strong", {}, t.label), t.note ? ` ${t.note}` : "", h("br", {}),
        h("span", { class: "muted" }, `(${fmt(t.world_mm)}) mm LPS`)),
      ...(o.canWrite ? [h("button", { class: "btn", "data-testid": "tag-delete", "data-write": "", onclick: () => void save(tags.filter((_, k) => k !== i), `Deleted ${t.label}.`) }, "Delete")] : []))));
  };
  const adopt = (s: TagSet, said: string) => {
    tags = s.tags;
    status.textContent = said;
    paintList();
    redraw();
  };
  const save = async (next: Tag[], said: string) => {
    if (busy) return;
    busy = true;
    try {
      const s = await apiJson<TagSet>("POST", `/api/cases/${o.caseId}/tags`, tagsBody(next, o.registrationId));
      adopt(s, `${said} Revision ${s.revision}: ${s.tags.length} tag(s), each on the brain surface.`);
    } catch (e) {
      o.showError(e); // e.g. "the photo pixel's ray misses the brain surface": the list stays as it was
    } finally { busy = false; }
  };
  placeBtn.addEventListener("click", async () => {
    placing = !placing;
    placeBtn.classList.toggle("active", placing);
    placeBtn.textContent = placing ? "Placing: tap the photo" : "Place tag";
    svg.classList.toggle("placing", placing);
    if (placing && !o.atCamera()) await o.toCamera(); // tags go on the photo: its camera's view
  });
  // A tap (a touch that moves under 8 px) while placing is a tag at that photo pixel; drags still turn the view.
  let down: { x: number; y: number } | null = null;
  // On the stage: its drag handler captures the pointer, so the overlay would not see the pointerup.
  o.stage.addEventListener("pointerdown", (e) => { down = { x: e.clientX, y: e.clientY }; });
  o.stage.addEventListener("pointerup", (e) => {
    const d = down;
    down = null;
    if (!placing || !d || Math.hypot(e.clientX - d.x, e.clientY - d.y) >= 8) return;
    if (!o.atCamera()) { status.textContent = "Tags are placed on the photo: tap Camera view first."; return; }
    const m = svg.getScreenCTM();
    if (!m) return;
    const pt = new DOMPoint(e.clientX, e.clientY).matrixTransform(m.inverse());
    const px = viewToPhotoPixel(pt.x - 0.5, pt.y - 0.5, o.K, o.viewW, o.viewH);
    if (px[0] < -0.5 || px[1] < -0.5 || px[0] > o.K.width - 0.5 || px[1] > o.K.height - 0.5) { status.textContent = "That tap is outside the photo."; return; }
    const t: Tag = { label: nextLabel(tags), colour, note: note.value.trim(), pixel: px };
    void save([...tags, t], `Placed ${t.label}.`).then(() => { note.value = ""; });
  });
  apiJson<TagSet>("GET", `/api/cases/${o.caseId}/tags`).then((s) => {
    const other = s.registration_id !== null && s.registration_id !== o.registrationId;
    adopt(s, s.tags.length ? `${s.tags.length} tag(s), revision ${s.revision}${other ? ` (placed with registration #${s.registration_id})` : ""}.` : "No tags yet.");
  }, o.showError);
  return { redraw, placing: () => placing };
}
