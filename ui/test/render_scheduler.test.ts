import { describe, expect, it } from "vitest";
import { fitFocalPx, RenderScheduler, renderSizes, type Size } from "../src/render_scheduler";

describe("render sizes", () => {
  it("the focal length fits the shorter side and scales with the picture", () => {
    expect(fitFocalPx(640, 480, 450, 110)).toBeCloseTo(0.5 * 480 * 450 / 110, 10);
    expect(fitFocalPx(480, 640, 450, 110)).toBeCloseTo(0.5 * 480 * 450 / 110, 10);
    expect(fitFocalPx(160, 120) * 4).toBeCloseTo(fitFocalPx(640, 480), 10);
  });
  it("full size from the element and the pixel ratio, preview a quarter", () => {
    const s = renderSizes(800, 600, 1, { width: 2048, height: 2048 });
    expect(s.full).toEqual({ width: 800, height: 600 });
    expect(s.preview).toEqual({ width: 200, height: 150 });
    expect(renderSizes(800, 600, 2, { width: 2048, height: 2048 }).full).toEqual({ width: 1600, height: 1200 });
  });
  it("clamps to the daemon's largest size keeping the aspect, and to at least 16", () => {
    expect(renderSizes(4000, 1000, 1, { width: 2000, height: 2000 }).full).toEqual({ width: 2000, height: 500 });
    expect(renderSizes(20, 10, 1, { width: 2048, height: 2048 }).preview).toEqual({ width: 16, height: 16 });
  });
});

// Manual timers and a render function whose answers the test releases.
function harness(settleMs = 200) {
  let now = 0;
  const timers: { at: number; fn: () => void; id: number }[] = [];
  let nextId = 1;
  const calls: { v: string; size: Size; resolve: (r: string) => void; reject: (e: unknown) => void }[] = [];
  const shown: { r: string; full: boolean }[] = [];
  const errors: unknown[] = [];
  const sched = new RenderScheduler<string>({
    render: (v, size) => new Promise((resolve, reject) => calls.push({ v, size, resolve: resolve as (r: string) => void, reject })),
    onImage: (r, _v, _s, full) => shown.push({ r: r as string, full }),
    onError: (e) => errors.push(e),
    sizes: () => ({ full: { width: 640, height: 480 }, preview: { width: 160, height: 120 } }),
    settleMs,
    timers: { set: (fn, ms) => { const id = nextId++; timers.push({ at: now + ms, fn, id }); return id; },
              clear: (id) => { const i = timers.findIndex((t) => t.id === id); if (i >= 0) timers.splice(i, 1); } },
  });
  const advance = (ms: number) => {
    now += ms;
    for (;;) {
      const due = timers.filter((t) => t.at <= now).sort((a, b) => a.at - b.at)[0];
      if (!due) break;
      timers.splice(timers.indexOf(due), 1);
      due.fn();
    }
  };
  const flush = () => new Promise((r) => setTimeout(r, 0));
  return { sched, calls, shown, errors, advance, flush };
}

describe("RenderScheduler", () => {
  it("a drag renders a small picture at once and the full size once it rests", async () => {
    const t = harness();
    t.sched.interactive("a");
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 160]]);
    t.calls[0].resolve("a-small");
    await t.flush();
    expect(t.shown).toEqual([{ r: "a-small", full: false }]);
    t.advance(199);
    expect(t.calls.length).toBe(1);
    t.advance(1);
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 160], ["a", 640]]);
    t.calls[1].resolve("a-full");
    await t.flush();
    expect(t.shown.at(-1)).toEqual({ r: "a-full", full: true });
  });

  it("one render in flight; during it only the newest view is kept", async () => {
    const t = harness();
    t.sched.interactive("a");
    t.sched.interactive("b");
    t.sched.interactive("c");
    expect(t.calls.length).toBe(1);
    expect(t.sched.inFlight).toBe(true);
    t.calls[0].resolve("a-small");
    await t.flush();
    expect(t.calls.map((c) => c.v)).toEqual(["a", "c"]); // b was superseded
    t.calls[1].resolve("c-small");
    await t.flush();
    t.advance(200);
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 160], ["c", 160], ["c", 640]]);
  });

  it("the settle timer restarts with each change; no full render of a stale view", async () => {
    const t = harness();
    t.sched.interactive("a");
    t.calls[0].resolve("a-small");
    await t.flush();
    t.advance(150);
    t.sched.interactive("b");
    t.advance(150); // 300 ms after a, 150 after b: nothing full yet
    expect(t.calls.filter((c) => c.size.width === 640).length).toBe(0);
    t.calls[1].resolve("b-small");
    await t.flush();
    t.advance(50);
    expect(t.calls.filter((c) => c.size.width === 640).map((c) => c.v)).toEqual(["b"]);
  });

  it("a button goes straight to full size and cancels a pending settle", async () => {
    const t = harness();
    t.sched.now("x");
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["x", 640]]);
    t.calls[0].resolve("x-full");
    await t.flush();
    t.sched.interactive("y");
    t.sched.now("z");
    t.calls[1].resolve("y-small");
    await t.flush();
    t.advance(1000);
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["x", 640], ["y", 160], ["z", 640]]);
  });

  it("an older answer arriving late never replaces a newer picture", async () => {
    const t = harness();
    t.sched.now("a");
    t.calls[0].resolve("a-full");
    await t.flush();
    t.sched.interactive("b");
    t.calls[1].resolve("b-small");
    await t.flush();
    expect(t.shown.map((s) => s.r)).toEqual(["a-full", "b-small"]);
  });

  it("reports a failed render and goes on with the next one", async () => {
    const t = harness();
    t.sched.now("a");
    t.sched.now("b");
    t.calls[0].reject(new Error("render failed"));
    await t.flush();
    expect((t.errors[0] as Error).message).toBe("render failed");
    expect(t.calls.map((c) => c.v)).toEqual(["a", "b"]);
    t.calls[1].resolve("b-full");
    await t.flush();
    expect(t.shown).toEqual([{ r: "b-full", full: true }]);
  });

  it("when the finger rests before the preview could start, the preview still comes first", async () => {
    const t = harness();
    t.sched.now("a"); // a slow full render in flight
    t.sched.interactive("b");
    t.advance(200); // rests while "a" still renders
    expect(t.calls.length).toBe(1);
    t.calls[0].resolve("a-full");
    await t.flush();
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 640], ["b", 160]]);
    t.calls[1].resolve("b-small");
    await t.flush();
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 640], ["b", 160], ["b", 640]]);
    t.calls[2].resolve("b-full");
    await t.flush();
    expect(t.shown.map((s) => s.r)).toEqual(["a-full", "b-small", "b-full"]);
  });
});

describe("RenderScheduler: buttons and overtaking a slow full render", () => {
  it("a button shows the preview first, then the full size at once (no rest)", async () => {
    const t = harness();
    t.sched.soon("a");
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 160]]);
    t.calls[0].resolve("a-small");
    await t.flush();
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 160], ["a", 640]]);
    t.calls[1].resolve("a-full");
    await t.flush();
    expect(t.shown).toEqual([{ r: "a-small", full: false }, { r: "a-full", full: true }]);
  });

  it("a button during a drag drops the drag's pending full render", async () => {
    const t = harness();
    t.sched.interactive("a");
    t.sched.soon("b");
    t.calls[0].resolve("a-small");
    await t.flush();
    t.advance(1000);
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 160], ["b", 160]]);
    t.calls[1].resolve("b-small");
    await t.flush();
    expect(t.calls.map((c) => [c.v, c.size.width])).toEqual([["a", 160], ["b", 160], ["b", 640]]);
  });

  it("without overtake a preview waits for the full render in flight", async () => {
    const t = harness();
    t.sched.now("a");
    t.sched.interactive("b");
    expect(t.calls.length).toBe(1);
  });

  it("with overtake a newer preview starts while an older full render is in flight; that one's answer is dropped", async () => {
    const shown: string[] = [];
    const errors: unknown[] = [];
    const calls: { v: string; w: number; resolve: (r: string) => void; reject: (e: unknown) => void }[] = [];
    const sched = new RenderScheduler<string>({
      render: (v, size) => new Promise((resolve, reject) => calls.push({ v, w: size.width, resolve: resolve as (r: string) => void, reject })),
      onImage: (r) => shown.push(r as string),
      onError: (e) => errors.push(e),
      sizes: () => ({ full: { width: 640, height: 480 }, preview: { width: 160, height: 120 } }),
      timers: { set: () => 0, clear: () => undefined },
      overtake: true,
      isSuperseded: (e) => e instanceof Error && e.message === "superseded",
    });
    sched.now("a");
    sched.interactive("b");
    sched.interactive("c");  // c waits for b: one preview at a time
    expect(calls.map((c) => [c.v, c.w])).toEqual([["a", 640], ["b", 160]]);
    calls[1].resolve("b-small");
    await new Promise((r) => setTimeout(r, 0));
    expect(calls.map((c) => [c.v, c.w])).toEqual([["a", 640], ["b", 160], ["c", 160]]);
    calls[0].reject(new Error("superseded"));  // the daemon gave the old full render up
    calls[2].resolve("c-small");
    await new Promise((r) => setTimeout(r, 0));
    expect(shown).toEqual(["b-small", "c-small"]);
    expect(errors).toEqual([]);  // a superseded render is no error to show
    // A full render that still finished after the newer preview is not shown.
    sched.now("d");
    sched.interactive("e");
    calls[4].resolve("e-small");
    await new Promise((r) => setTimeout(r, 0));
    calls[3].resolve("d-full");
    await new Promise((r) => setTimeout(r, 0));
    expect(shown).toEqual(["b-small", "c-small", "e-small"]);
    // Other errors are still reported.
    sched.now("f");
    expect(calls.at(-1)!.v).toBe("f");
    calls.at(-1)!.reject(new Error("render failed"));
    await new Promise((r) => setTimeout(r, 0));
    expect((errors[0] as Error).message).toBe("render failed");
  });
});
