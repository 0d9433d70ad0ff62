import { describe, expect, it } from "vitest";
import { LivePoller, type LiveFrame } from "../src/live_view";

/** A fake clock: sleep advances it at once; the fake camera answers frame seq+1 each time. */
function rig(opts: { failFirst?: number } = {}) {
  let t = 0, seq = 0, fails = opts.failFirst ?? 0;
  const urls: string[] = [];
  let inflight = 0, maxInflight = 0;
  const fetchImpl = async (url: string) => {
    urls.push(url);
    inflight++; maxInflight = Math.max(maxInflight, inflight);
    await new Promise((res) => setTimeout(res, 0)); // a macrotask: the test's waits get their turn
    t += 20; // each answer takes 20 ms
    inflight--;
    if (fails > 0) { fails--; return new Response(JSON.stringify({ error: { code: "unavailable", message: "camera live view: no new frame within 5000 ms (camera opening)" } }), { status: 503 }); }
    seq++;
    return new Response(new Blob([new Uint8Array([0xff, 0xd8, 0xff, 0xd9])], { type: "image/jpeg" }), { status: 200, headers: { "X-Frame-Seq": String(seq) } });
  };
  const sleeps: number[] = [];
  const sleep = async (ms: number) => { sleeps.push(ms); t += ms; await new Promise((res) => setTimeout(res, 0)); };
  return { fetchImpl, sleep, now: () => t, urls, sleeps, get maxInflight() { return maxInflight; }, get t() { return t; } };
}

async function until(cond: () => boolean) {
  for (let i = 0; i < 10000 && !cond(); i++) await new Promise((r) => setTimeout(r, 0));
}

describe("LivePoller", () => {
  it("asks for the frame after the one it has, one request at a time, at most 10 a second, and stops", async () => {
    const r = rig();
    const frames: LiveFrame[] = [];
    const p = new LivePoller((f) => frames.push(f), () => {}, { fetchImpl: r.fetchImpl, sleep: r.sleep, now: r.now, maxWidth: 640 });
    p.start();
    await until(() => frames.length >= 20);
    p.stop();
    const sent = r.urls.length;
    expect(frames.map((f) => f.seq).slice(0, 5)).toEqual([1, 2, 3, 4, 5]);
    expect(r.urls[0]).toBe("/api/camera/live?after=0&max_width=640");
    expect(r.urls[3]).toBe("/api/camera/live?after=3&max_width=640");
    expect(r.maxInflight).toBe(1);
    // 20 ms answers, paced to 100 ms a frame: 20 frames take about 2 s of the fake clock.
    const fps = frames.length / (r.t / 1000);
    expect(fps).toBeLessThanOrEqual(10.01);
    expect(fps).toBeGreaterThan(9);
    expect(r.sleeps.slice(0, 3)).toEqual([80, 80, 80]);
    // Stopped: no more requests.
    await new Promise((res) => setTimeout(res, 20));
    expect(r.urls.length).toBeLessThanOrEqual(sent + 1);
    expect(p.active).toBe(false);
  });

  it("says why when the daemon refuses, waits, and carries on", async () => {
    const r = rig({ failFirst: 2 });
    const frames: LiveFrame[] = [];
    const errors: string[] = [];
    const p = new LivePoller((f) => frames.push(f), (e) => errors.push((e as Error).message), { fetchImpl: r.fetchImpl, sleep: r.sleep, now: r.now, retryMs: 1000 });
    p.start();
    await until(() => frames.length >= 1);
    p.stop();
    expect(errors).toEqual([expect.stringContaining("camera opening"), expect.stringContaining("camera opening")]);
    expect(r.sleeps.slice(0, 2)).toEqual([1000, 1000]);
    expect(frames[0].seq).toBe(1);
  });
});
