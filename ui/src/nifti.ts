// Picking a point on the model's surface in the browser: the case's brain mask (a NIfTI-1 file
// from GET /api/cases/{id}/volumes/{vid}) is read here and a ray from the view's camera through
// the tapped pixel is marched to the first voxel inside it. Hand-written (≈ 100 lines): the npm
// NIfTI readers bring far more than this needs; the daemon has no pick endpoint yet.
// World coordinates are LPS mm as core uses them (ITK: the NIfTI qform, else the sform, RAS
// flipped to LPS).

export type M4 = number[][];
export interface Volume { dims: [number, number, number]; spacing: [number, number, number]; data: ArrayLike<number>; ijkToLps: M4; lpsToIjk: M4 }

const DTYPES: Record<number, [number, (v: DataView, o: number, le: boolean) => number]> = {
  2: [1, (v, o) => v.getUint8(o)], 256: [1, (v, o) => v.getInt8(o)],
  4: [2, (v, o, le) => v.getInt16(o, le)], 512: [2, (v, o, le) => v.getUint16(o, le)],
  8: [4, (v, o, le) => v.getInt32(o, le)], 768: [4, (v, o, le) => v.getUint32(o, le)],
  16: [4, (v, o, le) => v.getFloat32(o, le)], 64: [8, (v, o, le) => v.getFloat64(o, le)],
};

/** The bytes, gunzipped when they start with the gzip magic. */
export async function gunzipIfNeeded(buf: ArrayBuffer): Promise<ArrayBuffer> {
  const b = new Uint8Array(buf, 0, Math.min(2, buf.byteLength));
  if (b[0] !== 0x1f || b[1] !== 0x8b) return buf;
  const stream = new Blob([buf]).stream().pipeThrough(new DecompressionStream("gzip"));
  return new Response(stream).arrayBuffer();
}

export function invert4(m: M4): M4 {
  // Affine (last row 0 0 0 1): invert the 3x3 and the translation.
  const [a, b, c] = [m[0], m[1], m[2]];
  const det = a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0]);
  if (Math.abs(det) < 1e-12) throw new Error("the volume's orientation matrix is singular");
  const inv = [
    [(b[1] * c[2] - b[2] * c[1]) / det, (a[2] * c[1] - a[1] * c[2]) / det, (a[1] * b[2] - a[2] * b[1]) / det],
    [(b[2] * c[0] - b[0] * c[2]) / det, (a[0] * c[2] - a[2] * c[0]) / det, (a[2] * b[0] - a[0] * b[2]) / det],
    [(b[0] * c[1] - b[1] * c[0]) / det, (a[1] * c[0] - a[0] * c[1]) / det, (a[0] * b[1] - a[1] * b[0]) / det],
  ];
  const t = [0, 1, 2].map((r) => -(inv[r][0] * m[0][3] + inv[r][1] * m[1][3] + inv[r][2] * m[2][3]));
  return [[...inv[0], t[0]], [...inv[1], t[1]], [...inv[2], t[2]], [0, 0, 0, 1]];
}

export const apply4 = (m: M4, p: number[]): [number, number, number] =>
  [0, 1, 2].map((r) => m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]) as [number, number, number];

/** Reads a NIfTI-1 file (uncompressed bytes); throws naming what is wrong. */
export function parseNifti(buf: ArrayBuffer, name = "volume"): Volume {
  if (buf.byteLength < 352) throw new Error(`${name}: too short for a NIfTI-1 file`);
  const v = new DataView(buf);
  const le = v.getInt32(0, true) === 348;
  if (!le && v.getInt32(0, false) !== 348) throw new Error(`${name}: not a NIfTI-1 file (header size)`);
  const dim = [0, 1, 2, 3].map((i) => v.getInt16(40 + 2 * i, le));
  const dims: [number, number, number] = [dim[1], Math.max(1, dim[2]), Math.max(1, dim[3])];
  const dtype = v.getInt16(70, le);
  const dt = DTYPES[dtype];
  if (!dt) throw new Error(`${name}: voxel type ${dtype} is not read here`);
  const pix = [1, 2, 3].map((i) => Math.abs(v.getFloat32(76 + 4 * i, le)) || 1);
  const qfac = v.getFloat32(76, le) < 0 ? -1 : 1;
  const off = Math.max(352, Math.round(v.getFloat32(108, le)));
  let slope = v.getFloat32(112, le), inter = v.getFloat32(116, le);
  if (!slope || !Number.isFinite(slope)) { slope = 1; inter = 0; }
  const n = dims[0] * dims[1] * dims[2];
  if (off + n * dt[0] > buf.byteLength) throw new Error(`${name}: the voxel data is cut short`);
  const data = new Float32Array(n);
  for (let i = 0; i < n; i++) data[i] = dt[1](v, off + i * dt[0], le) * slope + inter;
  const qcode = v.getInt16(252, le), scode = v.getInt16(254, le);
  let ras: M4;
  if (qcode > 0) {
    const b = v.getFloat32(256, le), c = v.getFloat32(260, le), d = v.getFloat32(264, le);
    const a = Math.sqrt(Math.max(0, 1 - (b * b + c * c + d * d)));
    const R = [[a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
               [2 * (b * c + a * d), a * a + c * c - b * b - d * d, 2 * (c * d - a * b)],
               [2 * (b * d - a * c), 2 * (c * d + a * b), a * a + d * d - b * b - c * c]];
    const t = [268, 272, 276].map((o) => v.getFloat32(o, le));
    ras = [0, 1, 2].map((r) => [R[r][0] * pix[0], R[r][1] * pix[1], R[r][2] * pix[2] * qfac, t[r]]);
  } else if (scode > 0) {
    ras = [280, 296, 312].map((o) => [0, 1, 2, 3].map((k) => v.getFloat32(o + 4 * k, le)));
  } else {
    ras = [[pix[0], 0, 0, 0], [0, pix[1], 0, 0], [0, 0, pix[2], 0]];
  }
  const lps: M4 = [ras[0].map((x) => -x), ras[1].map((x) => -x), ras[2], [0, 0, 0, 1]];
  return { dims, spacing: pix as [number, number, number], data, ijkToLps: lps, lpsToIjk: invert4(lps) };
}

/** The voxel value nearest to an LPS point (0 outside). */
export function sampleAt(vol: Volume, lps: number[]): number {
  const [i, j, k] = apply4(vol.lpsToIjk, lps).map(Math.round);
  const [nx, ny, nz] = vol.dims;
  if (i < 0 || j < 0 || k < 0 || i >= nx || j >= ny || k >= nz) return 0;
  return vol.data[i + nx * (j + ny * k)];
}

/** The grid's centre in LPS mm (as GET /api/render/volume's center_lps_mm). */
export function centreLps(vol: Volume): [number, number, number] {
  return apply4(vol.ijkToLps, vol.dims.map((d) => (d - 1) / 2));
}

/** The first point along origin + t dir (t in [0, tMax] mm, dir a unit vector) where the
 *  volume is above `threshold`, refined to 0.05 mm; null when the ray misses. */
export function pickSurface(vol: Volume, origin: number[], dir: number[], tMax: number, threshold = 0.5, step = 0.5): [number, number, number] | null {
  const at = (t: number) => [origin[0] + t * dir[0], origin[1] + t * dir[1], origin[2] + t * dir[2]];
  let prev = 0;
  for (let t = 0; t <= tMax; t += step) {
    if (sampleAt(vol, at(t)) > threshold) {
      let lo = prev, hi = t;
      while (hi - lo > 0.05) { const m = (lo + hi) / 2; if (sampleAt(vol, at(m)) > threshold) hi = m; else lo = m; }
      return at(hi) as [number, number, number];
    }
    prev = t;
  }
  return null;
}

/** The ray (camera centre, unit direction in world) through pixel (u, v) of a camera with pose
 *  T_camera_from_world and pinhole intrinsics. */
export function pixelRay(T: M4, K: { fx: number; fy: number; cx: number; cy: number }, u: number, v: number): { origin: number[]; dir: number[] } {
  const dc = [(u - K.cx) / K.fx, (v - K.cy) / K.fy, 1];
  const l = Math.hypot(dc[0], dc[1], dc[2]);
  const R = [T[0].slice(0, 3), T[1].slice(0, 3), T[2].slice(0, 3)];
  const dir = [0, 1, 2].map((c) => (R[0][c] * dc[0] + R[1][c] * dc[1] + R[2][c] * dc[2]) / l);
  const origin = [0, 1, 2].map((c) => -(R[0][c] * T[0][3] + R[1][c] * T[1][3] + R[2][c] * T[2][3]));
  return { origin, dir };
}
