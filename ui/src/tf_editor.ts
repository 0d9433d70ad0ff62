// The transfer function editor: opacity (up) over normalised intensity (right) as a touch plot,
// each control point with its colour. Tap empty space to add a point, drag a point to move it,
// select one to give it a colour or delete it. Every change is handed on (`onChange`, `final`
// when the finger lifts) so the view re-renders while dragging. The model is tf_model.ts.
import { h } from "./dom";
import { addPoint, deletePoint, hitPoint, movePoint, pointsFromTf, rgbCss, setColour, tfFromPoints, type Rgb, type TfJson, type TfPoint } from "./tf_model";

// Colours a point can take (large swatches for gloved fingers): cortex, white matter, skin,
// bone, vessels/red, fMRI yellow, green, blue.
// Inner margin of the plot so that points at 0 and 1 are drawn (and touched) whole.
const PAD = 14;

const SWATCHES: [string, Rgb][] = [
  ["cortex", [0.95, 0.75, 0.7]], ["white", [1, 0.97, 0.92]], ["skin", [0.93, 0.7, 0.55]], ["bone", [0.96, 0.93, 0.8]],
  ["red", [0.9, 0.15, 0.1]], ["yellow", [1, 0.85, 0.1]], ["green", [0.2, 0.8, 0.3]], ["blue", [0.25, 0.5, 1]],
];

export class TfEditor {
  readonly el: HTMLElement;
  private readonly canvas: HTMLCanvasElement;
  private readonly info: HTMLElement;
  private readonly del: HTMLButtonElement;
  private points: TfPoint[] = [];
  private base: TfJson | null = null;
  private selected = -1;
  private drag: { id: number; moved: boolean } | null = null;
  private bars: number[] | null = null;

  constructor(private readonly onChange: (tf: TfJson, final: boolean) => void) {
    this.canvas = h("canvas", { class: "tf-canvas", "data-testid": "tf-canvas", "aria-label": "Transfer function: opacity over intensity" });
    this.info = h("span", { class: "muted", "data-testid": "tf-info" }, "Tap to add a point; drag to move it.");
    this.del = h("button", { class: "btn", "data-testid": "tf-delete", disabled: true }, "Delete point");
    this.del.addEventListener("click", () => {
      if (this.selected < 0) return;
      const next = deletePoint(this.points, this.selected);
      if (next === this.points) { this.info.textContent = "A transfer function needs at least two points."; return; }
      this.points = next;
      this.selected = -1;
      this.info.textContent = "Point deleted.";
      this.changed(true);
    });
    const swatches = h("div", { class: "tf-swatches", "data-testid": "tf-swatches" }, ...SWATCHES.map(([name, c]) => {
      const b = h("button", { class: "swatch", title: name, "aria-label": `colour ${name}`, "data-value": name });
      b.style.background = rgbCss(c);
      b.addEventListener("click", () => {
        if (this.selected < 0) { this.info.textContent = "Select a point first (tap it), then its colour."; return; }
        this.points = setColour(this.points, this.selected, c);
        this.changed(true);
      });
      return b;
    }));
    this.el = h("div", { class: "tf-editor", "data-testid": "tf-editor" }, this.canvas, h("div", { class: "tf-row" }, this.info, this.del), swatches);
    this.canvas.addEventListener("pointerdown", (e) => this.down(e));
    this.canvas.addEventListener("pointermove", (e) => this.move(e));
    this.canvas.addEventListener("pointerup", (e) => this.up(e));
    this.canvas.addEventListener("pointercancel", (e) => this.up(e));
    new ResizeObserver(() => this.draw()).observe(this.canvas);
  }

  /** Starts from a tf (a preset's JSON): its points, its units and gradient opacity. */
  load(tf: TfJson): void {
    this.base = tf;
    this.points = pointsFromTf(tf);
    this.selected = -1;
    this.draw();
  }

  /** The volume's intensity histogram under the points (heights 0..1 per equal bin of the
   *  normalised intensity 0..1, case_render.ts histogramBars); null removes it. */
  setHistogram(bars: number[] | null): void {
    this.bars = bars && bars.length ? bars : null;
    this.canvas.dataset.histogramBins = String(this.bars?.length ?? 0);
    this.draw();
  }

  get tf(): TfJson | null {
    return this.base ? tfFromPoints(this.points, this.base) : null;
  }

  private size(): { w: number; h: number } {
    return { w: this.canvas.clientWidth || 300, h: this.canvas.clientHeight || 160 };
  }

  /** The plot's inner size (points live in PAD..size-PAD). */
  private plot(): { w: number; h: number } {
    const { w, h: hh } = this.size();
    return { w: Math.max(1, w - 2 * PAD), h: Math.max(1, hh - 2 * PAD) };
  }

  private at(e: PointerEvent): { px: number; py: number; x: number; o: number } {
    const r = this.canvas.getBoundingClientRect();
    const { w, h: hh } = this.plot();
    const px = e.clientX - r.left - PAD, py = e.clientY - r.top - PAD;
    return { px, py, x: px / w, o: 1 - py / hh };
  }

  private down(e: PointerEvent): void {
    if (!this.base || this.drag) return;
    const p = this.at(e);
    const { w, h: hh } = this.plot();
    let i = hitPoint(this.points, p.px, p.py, w, hh);
    if (i < 0) {
      const r = addPoint(this.points, p.x, p.o);
      if (!r) return;
      this.points = r.points;
      i = r.index;
      this.changed(false);
    }
    this.selected = i;
    this.drag = { id: e.pointerId, moved: false };
    this.canvas.setPointerCapture(e.pointerId);
    this.draw();
  }

  private move(e: PointerEvent): void {
    if (!this.drag || e.pointerId !== this.drag.id || this.selected < 0) return;
    const p = this.at(e);
    this.points = movePoint(this.points, this.selected, p.x, p.o);
    this.drag.moved = true;
    this.changed(false);
  }

  private up(e: PointerEvent): void {
    if (!this.drag || e.pointerId !== this.drag.id) return;
    this.drag = null;
    this.changed(true);
  }

  private changed(final: boolean): void {
    this.draw();
    const tf = this.tf;
    if (tf) this.onChange(tf, final);
  }

  draw(): void {
    let { w, h: hh } = this.size();
    const dpr = window.devicePixelRatio || 1;
    if (this.canvas.width !== Math.round(w * dpr) || this.canvas.height !== Math.round(hh * dpr)) {
      this.canvas.width = Math.round(w * dpr);
      this.canvas.height = Math.round(hh * dpr);
    }
    const ctx = this.canvas.getContext("2d");
    this.canvas.dataset.points = String(this.points.length);
    this.canvas.dataset.selected = String(this.selected);
    this.del.disabled = this.selected < 0 || this.points.length <= 2;
    if (this.selected >= 0) {
      const p = this.points[this.selected];
      this.info.textContent = `Point ${this.selected + 1}: intensity ${(p.x * 100).toFixed(0)} %, opacity ${(p.opacity * 100).toFixed(0)} %`;
    }
    if (!ctx) return;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#0b0f14";
    ctx.fillRect(0, 0, w, hh);
    ctx.strokeStyle = "#26313d";
    ctx.lineWidth = 1;
    for (let k = 1; k < 4; k++) { ctx.beginPath(); ctx.moveTo(0, (k * hh) / 4); ctx.lineTo(w, (k * hh) / 4); ctx.stroke(); }
    const full = { w, h: hh };
    ctx.save();
    ctx.translate(PAD, PAD);
    ({ w, h: hh } = this.plot());
    if (this.bars) {
      // The histogram in the same units as the points: bin b spans x in [b, b + 1) / bins.
      const n = this.bars.length;
      ctx.fillStyle = "#3b4b5c";
      this.bars.forEach((v, b) => { if (v > 0) ctx.fillRect((b * w) / n, hh - v * hh, Math.max(1, w / n - 0.5), v * hh); });
    }
    if (!this.points.length) { ctx.restore(); return; }
    // The area under the opacity line, coloured as the points are.
    const grad = ctx.createLinearGradient(0, 0, w, 0);
    for (const p of this.points) grad.addColorStop(Math.max(0, Math.min(1, p.x)), rgbCss(p.colour));
    ctx.beginPath();
    ctx.moveTo(0, hh);
    ctx.lineTo(0, (1 - this.points[0].opacity) * hh);
    for (const p of this.points) ctx.lineTo(p.x * w, (1 - p.opacity) * hh);
    ctx.lineTo(w, (1 - this.points[this.points.length - 1].opacity) * hh);
    ctx.lineTo(w, hh);
    ctx.closePath();
    ctx.globalAlpha = 0.55;
    ctx.fillStyle = grad;
    ctx.fill();
    ctx.globalAlpha = 1;
    ctx.strokeStyle = "#e6edf3";
    ctx.lineWidth = 2;
    ctx.beginPath();
    this.points.forEach((p, i) => (i ? ctx.lineTo(p.x * w, (1 - p.opacity) * hh) : ctx.moveTo(p.x * w, (1 - p.opacity) * hh)));
    ctx.stroke();
    this.points.forEach((p, i) => {
      ctx.beginPath();
      ctx.arc(p.x * w, (1 - p.opacity) * hh, i === this.selected ? 14 : 11, 0, 2 * Math.PI);
      ctx.fillStyle = rgbCss(p.colour);
      ctx.fill();
      ctx.lineWidth = i === this.selected ? 4 : 2;
      ctx.strokeStyle = i === this.selected ? "#3d8bfd" : "#0b0f14";
      ctx.stroke();
    });
    ctx.restore();
    void full;
  }
}
