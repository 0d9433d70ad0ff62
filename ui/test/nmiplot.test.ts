import { describe, expect, it } from "vitest";
import { scalePlot } from "../src/nmiplot";

describe("NMI plot scaling", () => {
  it("maps the data range with a margin, higher NMI up", () => {
    const s = scalePlot([{ evaluation: 0, nmi: 1.05 }, { evaluation: 100, nmi: 1.15 }], 400, 200, 10);
    expect(s.yMin).toBeCloseTo(1.04, 10);
    expect(s.yMax).toBeCloseTo(1.16, 10);
    expect(s.xMax).toBe(100);
    expect(s.toX(0)).toBe(10);
    expect(s.toX(100)).toBe(390);
    expect(s.toX(50)).toBe(200);
    expect(s.toY(s.yMax)).toBeCloseTo(10, 10);
    expect(s.toY(s.yMin)).toBeCloseTo(190, 10);
    expect(s.toY(1.15)).toBeLessThan(s.toY(1.05));
  });

  it("keeps a minimum span for flat data and at least 10 evaluations", () => {
    const s = scalePlot([{ evaluation: 1, nmi: 1.2 }], 100, 100, 0);
    expect(s.yMax - s.yMin).toBeGreaterThanOrEqual(0.01);
    expect((s.yMax + s.yMin) / 2).toBeCloseTo(1.2, 10);
    expect(s.xMax).toBe(10);
    expect(Number.isFinite(s.toY(1.2))).toBe(true);
  });

  it("clamps to NMI's range [1, 2] and keeps points inside the box", () => {
    const s = scalePlot([{ evaluation: 0, nmi: 1.0 }, { evaluation: 5, nmi: 2.0 }], 100, 100, 5);
    expect(s.yMin).toBe(1);
    expect(s.yMax).toBe(2);
    const t = scalePlot([{ evaluation: 0, nmi: 1.0 }, { evaluation: 5, nmi: 1.001 }], 100, 100, 5);
    expect(t.yMin).toBe(1);
    expect(t.yMax - t.yMin).toBeGreaterThanOrEqual(0.01 - 1e-12);
    for (const y of [t.toY(0.5), t.toY(3)]) { expect(y).toBeGreaterThanOrEqual(5); expect(y).toBeLessThanOrEqual(95); }
    expect(t.toX(-4)).toBe(5);
    expect(t.toX(1e6)).toBe(95);
  });

  it("handles no points and ignores non-finite ones", () => {
    const s = scalePlot([], 100, 50);
    expect([s.yMin < s.yMax, s.xMax]).toEqual([true, 10]);
    const t = scalePlot([{ evaluation: NaN, nmi: 1.1 }, { evaluation: 3, nmi: Infinity }, { evaluation: 4, nmi: 1.3 }], 100, 50, 0);
    expect((t.yMax + t.yMin) / 2).toBeCloseTo(1.3, 10);
  });
});
