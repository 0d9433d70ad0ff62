// Marks on the photo: landmark twins (pixels) and the ROI, a closed cardinal spline through
// control points (docs/case-format.md roi.json: tension 0 is Catmull-Rom). Pixel coordinates
// have the centre of the top-left pixel at (0, 0), as core and the API use them. Pure
// functions: unit-tested.

export type Px = [number, number];

/** The SVG path of the closed cardinal spline through `pts` (pixel coordinates), as cubic
 *  Bezier segments: the tangent at P_i is (1 - tension)/2 (P_{i+1} - P_{i-1}). */
export function cardinalPath(pts: Px[], tension = 0): string {
  const n = pts.length;
  if (n === 0) return "";
  const f = (v: number) => (Math.round(v * 100) / 100).toString();
  if (n < 3) return `M${f(pts[0][0])},${f(pts[0][1])}` + pts.slice(1).map((p) => ` L${f(p[0])},${f(p[1])}`).join("");
  const k = (1 - tension) / 6;
  let d = `M${f(pts[0][0])},${f(pts[0][1])}`;
  for (let i = 0; i < n; i++) {
    const p0 = pts[(i - 1 + n) % n], p1 = pts[i], p2 = pts[(i + 1) % n], p3 = pts[(i + 2) % n];
    const c1: Px = [p1[0] + k * (p2[0] - p0[0]), p1[1] + k * (p2[1] - p0[1])];
    const c2: Px = [p2[0] - k * (p3[0] - p1[0]), p2[1] - k * (p3[1] - p1[1])];
    d += ` C${f(c1[0])},${f(c1[1])} ${f(c2[0])},${f(c2[1])} ${f(p2[0])},${f(p2[1])}`;
  }
  return d + " Z";
}

/** The point of the closed cardinal spline between P_i and P_{i+1} at parameter s in [0, 1]. */
export function cardinalPoint(pts: Px[], i: number, s: number, tension = 0): Px {
  const n = pts.length;
  const p0 = pts[(i - 1 + n) % n], p1 = pts[i % n], p2 = pts[(i + 1) % n], p3 = pts[(i + 2) % n];
  const k = (1 - tension) / 6;
  const c1: Px = [p1[0] + k * (p2[0] - p0[0]), p1[1] + k * (p2[1] - p0[1])];
  const c2: Px = [p2[0] - k * (p3[0] - p1[0]), p2[1] - k * (p3[1] - p1[1])];
  const u = 1 - s;
  const b = (a: number, b1: number, b2: number, c: number) => u * u * u * a + 3 * u * u * s * b1 + 3 * u * s * s * b2 + s * s * s * c;
  return [b(p1[0], c1[0], c2[0], p2[0]), b(p1[1], c1[1], c2[1], p2[1])];
}

/** Index of the point within `radius` of p (nearest), or -1. */
export function nearest(pts: Px[], p: Px, radius: number): number {
  let best = -1, bd = radius;
  pts.forEach((q, i) => { const d = Math.hypot(q[0] - p[0], q[1] - p[1]); if (d <= bd) { best = i; bd = d; } });
  return best;
}

/** Inserts p into the closed outline where it lengthens it least (a tap beside an edge goes
 *  into that edge); appends while there are fewer than 3 points. Returns the new list and p's index. */
export function insertRoiPoint(pts: Px[], p: Px): { points: Px[]; index: number } {
  if (pts.length < 3) return { points: [...pts, p], index: pts.length };
  let best = 0, bestCost = Infinity;
  for (let i = 0; i < pts.length; i++) {
    const a = pts[i], b = pts[(i + 1) % pts.length];
    const cost = Math.hypot(p[0] - a[0], p[1] - a[1]) + Math.hypot(b[0] - p[0], b[1] - p[1]) - Math.hypot(b[0] - a[0], b[1] - a[1]);
    if (cost < bestCost) { bestCost = cost; best = i; }
  }
  const out = [...pts.slice(0, best + 1), p, ...pts.slice(best + 1)];
  return { points: out, index: best + 1 };
}

/** Keeps a pixel inside a w x h photo (-0.5 .. w-0.5, as the daemon checks). */
export function clampPx(p: Px, w: number, h: number): Px {
  return [Math.max(-0.5, Math.min(w - 0.5, p[0])), Math.max(-0.5, Math.min(h - 0.5, p[1]))];
}

/** Projects a world point (LPS mm) with T_camera_from_world and pinhole intrinsics (no
 *  distortion) to a pixel; null behind the camera. */
export function projectPoint(T: number[][], K: { fx: number; fy: number; cx: number; cy: number }, X: number[]): Px | null {
  const c = [0, 1, 2].map((r) => T[r][0] * X[0] + T[r][1] * X[1] + T[r][2] * X[2] + T[r][3]);
  if (c[2] <= 1e-9) return null;
  return [K.fx * (c[0] / c[2]) + K.cx, K.fy * (c[1] / c[2]) + K.cy];
}

/** Intrinsics for an uploaded photo of w x h px when none are known: principal point at the
 *  centre, the focal length given (px). */
export function defaultCamera(w: number, h: number, focalPx: number) {
  return { width: w, height: h, fx: focalPx, fy: focalPx, cx: (w - 1) / 2, cy: (h - 1) / 2, distortion: [0, 0, 0, 0, 0] };
}

/** What a photo file is by its first bytes (the daemon checks too; this says so before the
 *  upload): "png", "jpeg" or null. */
export function imageKind(head: Uint8Array): "png" | "jpeg" | null {
  const png = [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a];
  if (head.length >= 8 && png.every((b, i) => head[i] === b)) return "png";
  if (head.length >= 3 && head[0] === 0xff && head[1] === 0xd8 && head[2] === 0xff) return "jpeg";
  return null;
}
