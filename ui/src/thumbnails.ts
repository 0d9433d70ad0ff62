// The case archive's thumbnails (issue 7, 7.2): GET /api/cases/{id}/thumbnail per row, a JPEG
// of the case's fused view, else of its photo (the daemon says which in X-Thumbnail-Source);
// 404 when the case has neither, shown as a neutral placeholder saying so. At most two
// requests at a time (a fused thumbnail is a render on the daemon's render thread); answers
// kept for the tab per case and its last change, so a search or re-sort asks nothing again.
// No DOM here: unit-tested.
import { auth, errorFromAnswer, plainMessage, type FetchLike } from "./api";

export type ThumbSource = "fused" | "photo" | "none" | "error";
export interface Thumb {
  source: ThumbSource;
  url: string | null; // an object URL of the JPEG; null for none/error
  note: string; // why a registered case shows its photo, the placeholder's words, or the error
}

/** The caption under a thumbnail. */
export function thumbCaption(t: Thumb): string {
  switch (t.source) {
    case "fused": return "Fused view";
    case "photo": return t.note ? "Photo (no fused view: see tooltip)" : "Photo";
    case "none": return "No photo or fused view yet";
    default: return "Picture not available";
  }
}

export class ThumbnailLoader {
  private readonly cache = new Map<string, Promise<Thumb>>();
  private running = 0;
  private readonly waiting: (() => void)[] = [];
  constructor(
    // A wrapper: window.fetch called as a method of another object throws "Illegal invocation".
    private readonly fetchImpl: FetchLike = (input, init) => fetch(input, init),
    private readonly makeUrl: (b: Blob) => string = (b) => URL.createObjectURL(b),
    readonly maxInFlight = 2,
  ) {}

  /** The thumbnail of case `id` as of its change `updatedUtc` (a newer change asks again). */
  get(id: number, updatedUtc: string): Promise<Thumb> {
    const key = `${id}@${updatedUtc}`;
    let p = this.cache.get(key);
    if (!p) {
      p = this.queue(() => this.fetchOne(id));
      this.cache.set(key, p);
    }
    return p;
  }

  /** Requests now in flight (for tests). */
  get inFlight(): number { return this.running; }

  private async queue<T>(f: () => Promise<T>): Promise<T> {
    if (this.running >= this.maxInFlight) await new Promise<void>((r) => this.waiting.push(r));
    this.running++;
    try {
      return await f();
    } finally {
      this.running--;
      this.waiting.shift()?.();
    }
  }

  private async fetchOne(id: number): Promise<Thumb> {
    const path = `/api/cases/${id}/thumbnail`;
    const headers: Record<string, string> = {};
    if (auth.token) headers["Authorization"] = `Bearer ${auth.token}`;
    try {
      const res = await this.fetchImpl(path, { method: "GET", headers });
      if (res.status === 404) {
        const e = errorFromAnswer("GET", path, 404, await res.text().catch(() => ""));
        // An unknown case would say "no such case"; a case without pictures says so.
        return /no photo or fused view/.test(e.message) ? { source: "none", url: null, note: "No photo or fused view yet" } : { source: "error", url: null, note: e.message };
      }
      if (!res.ok) return { source: "error", url: null, note: errorFromAnswer("GET", path, res.status, await res.text().catch(() => "")).message };
      const source = res.headers.get("X-Thumbnail-Source") === "fused" ? "fused" : "photo";
      return { source, url: this.makeUrl(await res.blob()), note: res.headers.get("X-Thumbnail-Note") ?? "" };
    } catch (e) {
      return { source: "error", url: null, note: plainMessage(e) };
    }
  }
}
