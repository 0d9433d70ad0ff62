// The camera's live view on the Photo screen (issue 7; docs/api/camera.md): the newest frame
// polled from GET /api/camera/live with ?after=SEQ (one request in flight, at most 10 frames a
// second), stopped when the screen is left (the daemon stops the stream 2 s after the last
// request), and a big Capture button that stores a still as the case's photo, as the Contents
// screen's "Capture from camera" does.
import { apiBlob, apiUpload, auth, errorFromAnswer, UserMessage, type FetchLike } from "./api";
import { h } from "./dom";
import { defaultCamera } from "./photo_marks";
import "./live_view.css";

export interface LiveFrame { blob: Blob; seq: number }

/** Polls the live frames. `sleep` and `now` are injectable for the unit tests. */
export class LivePoller {
  private running = false;
  private seq = 0;
  private inFlight = 0;
  requests = 0; // requests sent (tests)
  constructor(
    private readonly onFrame: (f: LiveFrame) => void,
    private readonly onError: (e: unknown) => void,
    private readonly opts: { maxFps?: number; maxWidth?: number; retryMs?: number; fetchImpl?: FetchLike;
                             sleep?: (ms: number) => Promise<void>; now?: () => number } = {},
  ) {}

  get active(): boolean { return this.running; }
  get inflight(): number { return this.inFlight; }

  start(): void {
    if (this.running) return;
    this.running = true;
    void this.loop();
  }
  stop(): void { this.running = false; }

  private async loop(): Promise<void> {
    const minGapMs = 1000 / (this.opts.maxFps ?? 10);
    const sleep = this.opts.sleep ?? ((ms: number) => new Promise<void>((r) => setTimeout(r, ms)));
    const now = this.opts.now ?? (() => performance.now());
    const fetchImpl = this.opts.fetchImpl ?? fetch;
    while (this.running) {
      const t0 = now();
      try {
        this.inFlight++;
        this.requests++;
        const path = `/api/camera/live?after=${this.seq}&max_width=${this.opts.maxWidth ?? 960}`;
        const init: RequestInit = { headers: auth.token ? { Authorization: `Bearer ${auth.token}` } : {} };
        const res = await fetchImpl(path, init);
        if (!res.ok) throw errorFromAnswer("GET", "/api/camera/live", res.status, await res.text().catch(() => ""));
        const seq = Number(res.headers.get("X-Frame-Seq") ?? NaN);
        const blob = await res.blob();
        this.inFlight--;
        if (!this.running) break;
        if (Number.isFinite(seq) && seq > this.seq) {
          this.seq = seq;
          this.onFrame({ blob, seq });
        }
      } catch (e) {
        this.inFlight--;
        if (!this.running) break;
        this.onError(e);
        await sleep(this.opts.retryMs ?? 1000);
        continue;
      }
      const wait = minGapMs - (now() - t0);
      if (wait > 0) await sleep(wait);
    }
  }
}

/** The Photo screen's camera panel: Live view (on/off) over `stage`, Capture. `onCaptured` after a
 *  photo is stored (the screen reloads). Stops with `stop()` (call it when the screen is left). */
export function mountLiveView(caseId: number, stage: HTMLElement, panel: HTMLElement, onCaptured: () => void, showError: (e: unknown) => void): { stop: () => void } {
  const img = h("img", { class: "live-frame", alt: "Live view of the camera", draggable: "false", "data-testid": "live-frame", hidden: true });
  stage.append(img);
  const status = h("p", { class: "muted", "data-testid": "live-status" }, "");
  const toggle = h("button", { class: "btn", "data-testid": "live-toggle" }, "Live view");
  const focal = h("input", { type: "number", class: "field narrow", min: 10, max: 100000, step: 1, value: 1400, title: "focal length (px)", "data-testid": "live-focal" });
  const capture = h("button", { class: "btn primary big", "data-testid": "live-capture" }, "Capture");
  // First in the panel: Capture is in reach without scrolling at 1280x800.
  panel.prepend(h("div", { class: "live-panel" }, h("h2", {}, "Camera"), h("div", { class: "choices" }, toggle), capture,
    h("div", { class: "toolbar" }, h("label", { class: "muted" }, "focal px"), focal), status));
  let url = "";
  let frames = 0, t0 = 0;
  const poller = new LivePoller((f) => {
    const u = URL.createObjectURL(f.blob);
    img.onload = () => { if (url) URL.revokeObjectURL(url); url = u; };
    img.src = u;
    img.hidden = false;
    img.dataset.seq = String(f.seq);
    frames++;
    const s = (performance.now() - t0) / 1000;
    status.textContent = `Live: frame ${f.seq}, ${s > 0.5 ? (frames / s).toFixed(1) : "–"} frames/s.`;
  }, (e) => {
    status.textContent = `No live view: ${e instanceof Error ? e.message : String(e)} (retrying).`;
  });
  const setLive = (on: boolean) => {
    if (on) { frames = 0; t0 = performance.now(); poller.start(); status.textContent = "Starting the live view (the first frame can take a few seconds)…"; }
    else { poller.stop(); img.hidden = true; status.textContent = "Live view off."; }
    toggle.classList.toggle("active", on);
    toggle.textContent = on ? "Live view: on" : "Live view";
    stage.classList.toggle("live", on);
  };
  toggle.addEventListener("click", () => setLive(!poller.active));
  capture.addEventListener("click", async () => {
    capture.disabled = true;
    status.textContent = "Taking a photo…";
    try {
      const blob = await apiBlob("/api/camera/capture", fetch, "POST");
      let bmp: ImageBitmap;
      try { bmp = await createImageBitmap(blob); } catch { throw new UserMessage("The camera's picture cannot be decoded; try again, or pick a file."); }
      const cam = defaultCamera(bmp.width, bmp.height, Number(focal.value) || 1400);
      bmp.close();
      const name = `capture_${new Date().toISOString().replace(/[-:]/g, "").replace(/\..*$/, "")}.${blob.type === "image/png" ? "png" : "jpg"}`;
      await apiUpload(`/api/cases/${caseId}/photos?name=${encodeURIComponent(name)}&camera=${encodeURIComponent(JSON.stringify(cam))}`, blob);
      status.textContent = `Photo stored (${cam.width}x${cam.height}).`;
      setLive(false);
      onCaptured();
    } catch (e) {
      status.textContent = "";
      showError(e);
    } finally { capture.disabled = false; }
  });
  return { stop: () => { poller.stop(); if (url) URL.revokeObjectURL(url); } };
}
