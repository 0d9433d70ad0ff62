// Re-rendering while the user drags: a small picture at once, the full one when the finger
// rests (issue 7: a new picture within 150 ms, refined after). One request in flight at a time;
// only the newest wanted view is kept, older answers are dropped.

export interface Size { width: number; height: number }

/** The full and preview sizes for a view element of w x h CSS px (dpr: device pixel ratio),
 *  each side within [16, max]; the preview is `previewScale` of the full size. */
export function renderSizes(w: number, h: number, dpr: number, max: Size, previewScale = 0.25): { full: Size; preview: Size } {
  const clamp = (v: number, hi: number) => Math.max(16, Math.min(hi, Math.round(v)));
  let fw = w * Math.max(1, dpr), fh = h * Math.max(1, dpr);
  const k = Math.min(1, max.width / fw, max.height / fh); // keep the aspect when clamping
  fw *= k; fh *= k;
  const full = { width: clamp(fw, max.width), height: clamp(fh, max.height) };
  const preview = { width: clamp(full.width * previewScale, max.width), height: clamp(full.height * previewScale, max.height) };
  return { full, preview };
}

export interface Timers {
  set: (fn: () => void, ms: number) => unknown;
  clear: (handle: unknown) => void;
}

export interface SchedulerOptions<V, R> {
  /** Renders view `v` at `size`; the scheduler never has two of these running. */
  render: (v: V, size: Size) => Promise<R>;
  onImage: (r: R, v: V, size: Size, full: boolean) => void;
  onError: (e: unknown) => void;
  sizes: () => { full: Size; preview: Size };
  /** Rest time after the last change before the full-size render. */
  settleMs?: number;
  timers?: Timers;
  /** A preview of a newer view may start while a full-size render of an older one is in flight
   *  (the daemon gives that one up when both carry the same `stream`; docs/api/render.md), so a
   *  touch during the slow full render still shows a picture at once. */
  overtake?: boolean;
  /** An error that only says the render was given up for a newer view: not reported. */
  isSuperseded?: (e: unknown) => boolean;
}

export class RenderScheduler<V> {
  // What to render next, in order: at most [preview, full] of the newest view.
  private queue: { v: V; full: boolean; gen: number }[] = [];
  private inflight: { gen: number; full: boolean }[] = [];
  private gen = 0;
  private shownGen = -1;
  private settle: unknown = null;
  private readonly timers: Timers;
  private readonly settleMs: number;

  constructor(private readonly o: SchedulerOptions<V, unknown>) {
    this.timers = o.timers ?? { set: (fn, ms) => setTimeout(fn, ms), clear: (h) => clearTimeout(h as number) };
    this.settleMs = o.settleMs ?? 200;
  }

  /** The view changed during a gesture: a preview now, the full size once it rests. */
  interactive(v: V): void {
    const gen = ++this.gen;
    this.queue = [{ v, full: false, gen }];
    if (this.settle !== null) this.timers.clear(this.settle);
    this.settle = this.timers.set(() => {
      this.settle = null;
      if (this.gen !== gen) return;
      // The preview of this view still waiting (a render was in flight): it goes first.
      const waiting = this.queue.length === 1 && this.queue[0].gen === gen && !this.queue[0].full;
      this.queue = waiting ? [this.queue[0], { v, full: true, gen }] : [{ v, full: true, gen }];
      this.pump();
    }, this.settleMs);
    this.pump();
  }

  /** The view changed by a button (a step, no gesture): the preview at once, then the full
   *  size right after it (no rest to wait for). */
  soon(v: V): void {
    if (this.settle !== null) { this.timers.clear(this.settle); this.settle = null; }
    const gen = ++this.gen;
    this.queue = [{ v, full: false, gen }, { v, full: true, gen }];
    this.pump();
  }

  /** Straight to full size (no preview). */
  now(v: V): void {
    if (this.settle !== null) { this.timers.clear(this.settle); this.settle = null; }
    this.queue = [{ v, full: true, gen: ++this.gen }];
    this.pump();
  }

  get inFlight(): boolean {
    return this.inflight.length > 0;
  }

  private canStart(next: { full: boolean; gen: number }): boolean {
    if (!this.inflight.length) return true;
    return !!this.o.overtake && !next.full && this.inflight.length < 2 && this.inflight.every((f) => f.full && f.gen < next.gen);
  }

  private pump(): void {
    if (!this.queue.length || !this.canStart(this.queue[0])) return;
    const w = this.queue.shift()!;
    const sizes = this.o.sizes();
    const size = w.full ? sizes.full : sizes.preview;
    const mine = { gen: w.gen, full: w.full };
    this.inflight.push(mine);
    this.o.render(w.v, size).then(
      (r) => {
        // Drop an answer older than what is shown (a full picture is never replaced by an older preview).
        if (w.gen > this.shownGen || (w.gen === this.shownGen && w.full)) {
          this.shownGen = w.gen;
          this.o.onImage(r, w.v, size, w.full);
        }
      },
      (e) => { if (!this.o.isSuperseded?.(e)) this.o.onError(e); },
    ).finally(() => {
      this.inflight = this.inflight.filter((f) => f !== mine);
      this.pump();
    });
  }
}

/** Focal length (px) that fits `halfExtentMm` round the volume's centre into the shorter side
 *  of a width x height picture seen from `distanceMm` (the daemon's default fits the width only,
 *  which crops the head in a wide view). Proportional to the size, so preview and full agree. */
export function fitFocalPx(width: number, height: number, distanceMm = 450, halfExtentMm = 95): number {
  return (0.5 * Math.min(width, height) * distanceMm) / halfExtentMm;
}
