import { describe, expect, it } from "vitest";
import {
  applyT, canRegister, fiducialLines, freVerdict, needsNewSlices, nextFiducial, pivotLine, pointerInImage, rateView, sliceCaptionText, slicesPath, tipLine, toolView, toolViews,
  type NavState, type PointerAnswer, type Registration, type ToolJson, type Vec3,
} from "../src/tracker_model";

const nav = (recorded: string[], labels = ["nasion", "left", "right", "vertex"]): NavState => ({
  case_id: 1, state: "new",
  image_fiducials: { revision: 3, fiducials: labels.map((l, i) => ({ label: l, p_image_mm: [i * 10, 0, 0] as Vec3 })) },
  patient_fiducials: { revision: 5, fiducials: recorded.map((l) => ({ label: l, p_reference_mm: [0, 0, 0] as Vec3, spread_mm: 0.1, frames: 18 })) },
  accepted: null, accepted_count: 0,
});

// 90 degrees about z, then a shift: image = R * reference + t.
const T: number[][] = [[0, -1, 0, 10], [1, 0, 0, 20], [0, 0, 1, 30], [0, 0, 0, 1]];
const reg = (rows: { label: string; residual_mm: number; used: boolean }[]): Registration => ({
  T_image_from_reference: T, fre_mm: 0.4, fle_mm: 0.5, n_used: rows.filter((r) => r.used).length,
  fiducials: rows.map((r) => ({ ...r, p_image_mm: [0, 0, 0] as Vec3, p_reference_mm: [0, 0, 0] as Vec3 })),
  excluded: rows.filter((r) => !r.used).map((r) => r.label), missing: [], predicted_tre_mm: 0.3, target: "centroid of the fiducials",
  image_fiducials_revision: 3, patient_fiducials_revision: 5, params: { outlier_mm: 5, fle_mm: 0 },
});

const answer = (tools: ToolJson[], extra: Partial<PointerAnswer> = {}): PointerAnswer => ({
  enabled: true, state: "streaming", frame_rate_hz: 59.6, frame: { seq: 10, frame: 100, tools }, age_ms: 5,
  p_reference_mm: [1, 2, 3], p_tracker_mm: [0, 0, -1400], tip_pointer_mm: [0, 0, 0], ...extra,
});

describe("tracker tools", () => {
  it("a seen tool is green with its RMS; missing, stale and out of volume are red and say so", () => {
    expect(toolView({ name: "pointer", status: "ok", rms_mm: 0.123 })).toEqual({ name: "pointer", text: "seen", level: "ok", rms: "0.12 mm" });
    expect(toolView({ name: "pointer", status: "missing" })).toMatchObject({ text: "missing (not seen)", level: "bad", rms: "—" });
    expect(toolView({ name: "pointer", status: "missing", stale: true })).toMatchObject({ text: expect.stringContaining("stale"), level: "bad" });
    expect(toolView({ name: "reference", status: "missing", out_of_volume: true }).text).toBe("out of the tracking volume");
    expect(toolView({ name: "reference", status: "ok", partially_out_of_volume: true, rms_mm: 0.2 }).level).toBe("warn");
  });

  it("an old frame makes every tool stale, whatever it said", () => {
    const v = toolView({ name: "pointer", status: "ok", rms_mm: 0.1 }, 1200);
    expect(v.level).toBe("bad");
    expect(v.text).toBe("stale (no frame for 1.2 s)");
  });

  it("no tracker or no frame is one red line", () => {
    expect(toolViews(null)[0]).toMatchObject({ name: "tracker", level: "bad", text: "disabled" });
    expect(toolViews(answer([], { frame: null, state: "connecting" }))[0].text).toBe("no frame yet (connecting)");
    const v = toolViews(answer([{ name: "reference", status: "ok", rms_mm: 0.1 }, { name: "pointer", status: "missing" }]));
    expect(v.map((x) => [x.name, x.level])).toEqual([["reference", "ok"], ["pointer", "bad"]]);
  });

  it("the rate is amber below 20 Hz and red at 0", () => {
    expect(rateView(answer([]))).toEqual({ text: "60 Hz (streaming)", level: "ok" });
    expect(rateView(answer([], { frame_rate_hz: 12 })).level).toBe("warn");
    expect(rateView(answer([], { frame_rate_hz: 0, state: "recovering" }))).toEqual({ text: "0 Hz (recovering)", level: "bad" });
  });
});

describe("pointer in the image", () => {
  it("maps the tip in the reference frame through T_image_from_reference", () => {
    expect(applyT(T, [1, 2, 3])).toEqual([8, 21, 33]);
    expect(pointerInImage(answer([]), reg([]))).toEqual([8, 21, 33]);
  });
  it("is null without a registration or without both tools", () => {
    expect(pointerInImage(answer([]), null)).toBeNull();
    expect(pointerInImage(answer([], { p_reference_mm: null }), reg([]))).toBeNull();
  });
});

describe("fiducials to touch", () => {
  it("the next one is the selected one, else the first not recorded, else none", () => {
    expect(nextFiducial(nav([]), null)).toBe("nasion");
    expect(nextFiducial(nav(["nasion", "left"]), null)).toBe("right");
    expect(nextFiducial(nav(["nasion", "left"]), "nasion")).toBe("nasion"); // re-record on request
    expect(nextFiducial(nav(["nasion", "left"]), "chin")).toBe("right"); // not in the list: ignored
    expect(nextFiducial(nav(["nasion", "left", "right", "vertex"]), null)).toBeNull();
  });

  it("registration needs 3 recorded fiducials that are in the image list", () => {
    expect(canRegister(nav(["nasion", "left"]))).toBe(false);
    expect(canRegister(nav(["nasion", "left", "chin"]))).toBe(false);
    expect(canRegister(nav(["nasion", "left", "right"]))).toBe(true);
  });

  it("each line says recorded, used with its residual, or excluded", () => {
    const lines = fiducialLines(nav(["nasion", "left", "right", "vertex"]),
      reg([{ label: "nasion", residual_mm: 0.3, used: true }, { label: "left", residual_mm: 2.5, used: true },
           { label: "right", residual_mm: 7.9, used: false }]));
    expect(lines.map((l) => [l.label, l.residual, l.level])).toEqual([
      ["nasion", "0.30 mm", "ok"], ["left", "2.50 mm", "warn"], ["right", "7.90 mm", "bad"], ["vertex", "", "ok"]]);
    expect(lines[2].note).toContain("excluded");
    expect(fiducialLines(nav([]), null).every((l) => !l.recorded && l.note === "to touch")).toBe(true);
  });

  it("the FRE verdict: good, acceptable, redo", () => {
    expect(freVerdict(0.42)).toEqual({ text: "FRE 0.42 mm: good", level: "ok" });
    expect(freVerdict(2).level).toBe("warn");
    expect(freVerdict(3.5).text).toContain("redo");
  });
});

describe("pointer tip", () => {
  it("says which tip is in use", () => {
    expect(tipLine(answer([], { tip_pointer_mm: [3, -2, -150], tip_source: "pivot calibration: rms 0.13 mm" })))
      .toBe("Pointer tip (3.00, -2.00, -150.00) mm in the pointer's frame: pivot calibration: rms 0.13 mm");
    expect(tipLine(null)).toContain("unknown");
  });
  it("a pivot answer in words, with its warning", () => {
    const p = { tip_pointer_mm: [1, 2, 3] as Vec3, rms_mm: 0.134, rotation_spread_deg: 15.44, poses: 150, warning: "", applied: true };
    expect(pivotLine(p)).toBe("Tip calibrated: (1.00, 2.00, 3.00) mm, rms 0.13 mm over 150 poses, swivelled 15.4°");
    expect(pivotLine({ ...p, applied: false, warning: "the pointer did not move enough" })).toMatch(/^Tip measured \(not applied\).*did not move enough$/);
  });
});

describe("slices", () => {
  it("ask again only when the point moved more than half a millimetre", () => {
    expect(needsNewSlices(null, [0, 0, 0])).toBe(true);
    expect(needsNewSlices([0, 0, 0], [0.3, 0.3, 0])).toBe(false);
    expect(needsNewSlices([0, 0, 0], [0.4, 0.4, 0])).toBe(true);
    expect(needsNewSlices([0, 0, 0], null)).toBe(false);
  });
  it("a failed slice request is said under the picture until one succeeds", () => {
    expect(sliceCaptionText("Pointer tip (1.0, 2.0, 3.0) mm (accepted registration)", "")).toBe("Pointer tip (1.0, 2.0, 3.0) mm (accepted registration)");
    expect(sliceCaptionText("Pointer tip (1.0, 2.0, 3.0) mm (accepted registration)", "GET /api/navigation/slices: the daemon is busy (HTTP 503)."))
      .toBe("Pointer tip (1.0, 2.0, 3.0) mm (accepted registration) The MRI slices could not be loaded (GET /api/navigation/slices: the daemon is busy (HTTP 503)); trying again every second.");
    expect(sliceCaptionText("", "no connection")).toBe("The MRI slices could not be loaded (no connection); trying again every second.");
  });
  it("the query names the point, size, field of view and format", () => {
    expect(slicesPath([1.234, -5, 60.05], 240)).toBe("/api/navigation/slices?x=1.23&y=-5.00&z=60.05&size=240&fov_mm=220&format=jpeg");
  });
});
