import { describe, expect, it } from "vitest";
import { nearestMarker, nextLabel, projectToView, tagsBody, viewToPhotoPixel, type Intrinsics, type Tag } from "../src/tags";

const K: Intrinsics = { width: 640, height: 480, fx: 800, fy: 800, cx: 319.5, cy: 239.5 };
// A camera 300 mm in front of the origin looking along +z (T_camera_from_world = translation).
const T = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 300], [0, 0, 0, 1]];

describe("tags", () => {
  it("projects a world point as the photo's camera resized to the view", () => {
    // At full size: x = fx * X / Z + cx.
    const full = projectToView(T, K, 640, 480, [30, -15, 0])!;
    expect(full.x).toBeCloseTo(800 * 30 / 300 + 319.5, 9);
    expect(full.y).toBeCloseTo(800 * -15 / 300 + 239.5, 9);
    expect(full.depthMm).toBeCloseTo(300, 9);
    // Half size: the same point lands on the same place of the picture (pixel centres scaled).
    const half = projectToView(T, K, 320, 240, [30, -15, 0])!;
    expect(half.x).toBeCloseTo((full.x + 0.5) / 2 - 0.5, 9);
    expect(half.y).toBeCloseTo((full.y + 0.5) / 2 - 0.5, 9);
    // And back to the photo pixel it shows.
    const px = viewToPhotoPixel(half.x, half.y, K, 320, 240);
    expect(px[0]).toBeCloseTo(full.x, 9);
    expect(px[1]).toBeCloseTo(full.y, 9);
  });

  it("hides points behind the camera and tells front from back faces", () => {
    expect(projectToView(T, K, 640, 480, [0, 0, -400])).toBeNull();
    expect(projectToView(T, K, 640, 480, [0, 0, 0], [0, 0, -1])!.facing).toBe(true); // normal towards the camera
    expect(projectToView(T, K, 640, 480, [0, 0, 0], [0, 0, 1])!.facing).toBe(false);
  });

  it("labels, request bodies and picking", () => {
    const tags: Tag[] = [
      { label: "S1", colour: "#ff4040", note: "", pixel: [1, 2], world_mm: [1, 2, 3], normal_world: [0, 0, 1] },
      { label: "S3", colour: "#ffffff", note: "hand", pixel: [5, 6] },
    ];
    expect(nextLabel(tags)).toBe("S2");
    expect(nextLabel([])).toBe("S1");
    // Only the marks go to the daemon (it recomputes the cast).
    expect(tagsBody(tags, 7)).toEqual({ tags: [{ label: "S1", colour: "#ff4040", note: "", pixel: [1, 2] }, { label: "S3", colour: "#ffffff", note: "hand", pixel: [5, 6] }], registration_id: 7 });
    expect(nearestMarker([{ x: 10, y: 10 }, null, { x: 30, y: 10 }], { x: 26, y: 12 }, 24)).toBe(2);
    expect(nearestMarker([{ x: 10, y: 10 }], { x: 100, y: 100 }, 24)).toBe(-1);
  });
});
