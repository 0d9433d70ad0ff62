// The transfer function editor's model: one list of control points over normalised intensity
// (x in [0, 1]), each with an opacity and a colour, read from and written to the JSON shape
// POST /api/render's `tf` takes (docs/api/render.md: separate `colour` [x, r, g, b] and
// `opacity` [x, o] lists, sorted by x). Pure functions: unit-tested.

export type Rgb = [number, number, number];
export interface TfPoint { x: number; opacity: number; colour: Rgb }
export interface TfJson {
  name?: string; units?: string;
  colour: number[][]; opacity: number[][]; gradient_opacity?: number[][];
}

/** Minimum spacing of two points on x (the daemon wants them sorted; equal x would make a step). */
export const MIN_GAP = 0.005;

const clamp01 = (v: number) => Math.max(0, Math.min(1, Number.isFinite(v) ? v : 0));

/** Piecewise-linear value at x of sorted [x, ...values] points (constant beyond the ends). */
export function interp(points: number[][], x: number): number[] {
  if (!points.length) return [];
  if (x <= points[0][0]) return points[0].slice(1);
  const last = points[points.length - 1];
  if (x >= last[0]) return last.slice(1);
  for (let i = 1; i < points.length; i++) {
    const a = points[i - 1], b = points[i];
    if (x <= b[0]) {
      const t = b[0] === a[0] ? 1 : (x - a[0]) / (b[0] - a[0]);
      return a.slice(1).map((v, k) => v + t * (b[k + 1] - v));
    }
  }
  return last.slice(1);
}

/** The editor's points from a tf (a preset's JSON): at every x where either list has a point,
 *  the opacity and the colour there; the same function, as both lists are piecewise linear. */
export function pointsFromTf(tf: TfJson): TfPoint[] {
  const xs = [...new Set([...tf.colour.map((p) => p[0]), ...tf.opacity.map((p) => p[0])])].sort((a, b) => a - b);
  return xs.map((x) => {
    const c = interp(tf.colour, x);
    return { x, opacity: clamp01(interp(tf.opacity, x)[0] ?? 0), colour: [clamp01(c[0] ?? 1), clamp01(c[1] ?? 1), clamp01(c[2] ?? 1)] };
  });
}

/** The tf JSON of the points; `base` gives units and gradient_opacity (kept as they were). */
export function tfFromPoints(points: TfPoint[], base?: Partial<TfJson>, name = "custom"): TfJson {
  const ps = [...points].sort((a, b) => a.x - b.x);
  const out: TfJson = {
    name, units: base?.units ?? "normalized",
    colour: ps.map((p) => [round(p.x), round(p.colour[0]), round(p.colour[1]), round(p.colour[2])]),
    opacity: ps.map((p) => [round(p.x), round(p.opacity)]),
  };
  if (base?.gradient_opacity?.length) out.gradient_opacity = base.gradient_opacity;
  return out;
}
const round = (v: number) => Math.round(v * 10000) / 10000;

/** Moves point i to (x, opacity): x stays between its neighbours (MIN_GAP apart) and in [0, 1]. */
export function movePoint(points: TfPoint[], i: number, x: number, opacity: number): TfPoint[] {
  const lo = i > 0 ? points[i - 1].x + MIN_GAP : 0;
  const hi = i < points.length - 1 ? points[i + 1].x - MIN_GAP : 1;
  const out = points.slice();
  out[i] = { ...points[i], x: Math.max(lo, Math.min(hi, clamp01(x))), opacity: clamp01(opacity) };
  return out;
}

/** Adds a point at x (its colour interpolated there); null when too close to another point. */
export function addPoint(points: TfPoint[], x: number, opacity: number): { points: TfPoint[]; index: number } | null {
  const cx = clamp01(x);
  if (points.some((p) => Math.abs(p.x - cx) < MIN_GAP)) return null;
  const c = interp(points.map((p) => [p.x, ...p.colour]), cx);
  const np: TfPoint = { x: cx, opacity: clamp01(opacity), colour: [c[0] ?? 1, c[1] ?? 1, c[2] ?? 1] };
  const out = [...points, np].sort((a, b) => a.x - b.x);
  return { points: out, index: out.indexOf(np) };
}

/** Removes point i; the last two points stay (a tf needs a line). */
export function deletePoint(points: TfPoint[], i: number): TfPoint[] {
  if (points.length <= 2 || i < 0 || i >= points.length) return points;
  return points.filter((_, k) => k !== i);
}

export function setColour(points: TfPoint[], i: number, colour: Rgb): TfPoint[] {
  const out = points.slice();
  out[i] = { ...points[i], colour: [clamp01(colour[0]), clamp01(colour[1]), clamp01(colour[2])] };
  return out;
}

/** The point under (px, py) in a w x h plot (x right, opacity up) within `radius` px, or -1. */
export function hitPoint(points: TfPoint[], px: number, py: number, w: number, h: number, radius = 24): number {
  let best = -1, bestD = radius;
  points.forEach((p, i) => {
    const d = Math.hypot(p.x * w - px, (1 - p.opacity) * h - py);
    if (d <= bestD) { best = i; bestD = d; }
  });
  return best;
}

export const rgbCss = (c: Rgb) => `rgb(${Math.round(c[0] * 255)}, ${Math.round(c[1] * 255)}, ${Math.round(c[2] * 255)})`;
