import { describe, expect, it } from "vitest";
import { AlignmentFetcher, alignmentBody, alignmentHeadline, highErrorPx, pairErrorText, type Alignment, type PairIn } from "../src/initial_alignment";

const pairs = (n: number): PairIn[] =>
  Array.from({ length: n }, (_, i) => ({ name: `L${i + 1}`, world_mm: [i, 2 * i, 3], pixel: [10 + i, 20 + i] }));

function answer(errors: number[]): Alignment {
  const rms = Math.sqrt(errors.reduce((s, e) => s + e * e, 0) / errors.length);
  return {
    case_id: 3, photo_id: 9, method: "pnp", T_camera_from_world: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 300], [0, 0, 0, 1]],
    rms_px: rms, max_error_px: Math.max(...errors), inliers: errors.map((_, i) => i),
    pairs: errors.map((e, i) => ({ label: `L${i + 1}`, world_mm: [i, 0, 0], pixel: [i, i], projected_pixel: [i + e, i], error_px: e })),
  };
}

/** A fetch whose answers the test releases one by one, in any order. */
function heldFetch() {
  const calls: { path: string; body: unknown; release: (status: number, body: unknown) => void }[] = [];
  const f = (path: string, init?: RequestInit) => new Promise<Response>((resolve) => {
    calls.push({ path, body: JSON.parse(String(init?.body)), release: (status, body) => resolve(new Response(JSON.stringify(body), { status })) });
  });
  return { f, calls };
}

describe("initial alignment", () => {
  it("sends the pairs on the screen with their photo and words the answer", () => {
    expect(alignmentBody(pairs(2), 9)).toEqual({
      landmarks: [{ label: "L1", world_mm: [0, 0, 3], pixel: [10, 20] }, { label: "L2", world_mm: [1, 2, 3], pixel: [11, 21] }], photo_id: 9,
    });
    expect(alignmentHeadline(null, 3, "")).toBe("Initial alignment: needs at least 4 pairs (3 now).");
    expect(alignmentHeadline(null, 5, "")).toBe("Initial alignment: computing…");
    const a = answer([1, 2, 7.5, 0.5]);
    expect(alignmentHeadline(a, 4, "")).toBe("Initial alignment from 4 pairs: reprojection RMS 3.92 px, worst L3 7.5 px (pnp).");
    // Pairs nearly on a line: the daemon's warning follows the numbers.
    const lined = { ...a, spread: { world: 0.07, pixel: 0.3 }, warning: "the landmarks lie nearly on a line (spread 0.07, under 0.15): add a pair away from the line" };
    expect(alignmentHeadline(lined, 4, "")).toBe("Initial alignment from 4 pairs: reprojection RMS 3.92 px, worst L3 7.5 px (pnp). Warning: the landmarks lie nearly on a line (spread 0.07, under 0.15): add a pair away from the line.");
    expect(alignmentHeadline({ ...a, warning: "" }, 4, "")).not.toContain("Warning");
    expect(alignmentHeadline(null, 4, "case 3 landmarks: landmark world points are collinear")).toContain("not possible with these pairs: case 3 landmarks: landmark world points are collinear");
    expect(pairErrorText(a, 2)).toBe("7.5 px");
    expect(pairErrorText(null, 0)).toBe("— px");
    expect(highErrorPx(200)).toBe(4);
    expect(highErrorPx(1920)).toBeCloseTo(28.8, 9);
  });

  it("asks after each change and keeps only the newest answer", async () => {
    const { f, calls } = heldFetch();
    let changes = 0;
    const fetcher = new AlignmentFetcher(3, () => { changes++; }, f as unknown as typeof fetch);
    // Fewer than four pairs: no request, the headline says why.
    await fetcher.update(pairs(3), 9);
    expect(calls).toHaveLength(0);
    expect(fetcher.pairCount).toBe(3);
    // Two edits in a row; the first answer arrives after the second: it is dropped.
    const first = fetcher.update(pairs(4), 9);
    const second = fetcher.update(pairs(5), 9);
    expect(calls).toHaveLength(2);
    expect(calls[0].path).toBe("/api/cases/3/landmarks/initial-pose");
    expect((calls[1].body as { landmarks: unknown[] }).landmarks).toHaveLength(5);
    calls[1].release(200, answer([1, 1, 1, 1, 1]));
    await second;
    calls[0].release(200, answer([9, 9, 9, 9]));
    await first;
    expect(fetcher.alignment?.pairs).toHaveLength(5);
    expect(fetcher.alignment?.rms_px).toBeCloseTo(1, 9);
    expect(changes).toBeGreaterThan(0);
    // A refusal: the daemon's words, no alignment.
    const third = fetcher.update(pairs(4), 9);
    calls[2].release(400, { error: { code: "bad_request", status: 400, message: "case 3 landmarks: landmark pixels are collinear; pick points that span an area" } });
    await third;
    expect(fetcher.alignment).toBeNull();
    expect(fetcher.error).toBe("case 3 landmarks: landmark pixels are collinear; pick points that span an area");
  });
});
