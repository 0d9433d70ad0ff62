// The plan's brain surface on the Preoperative quick check (issue 7, 7.6b): the stored
// plan_brain_surface (binary or ASCII PLY in world LPS mm, as core's VTK writer makes it) cut by
// the three slice planes of the mask picture, drawn as lines over the mask, and how much of that
// outline lies inside the mask (within 2 voxels): the plan's surface is an isosurface of the T1
// within the brain mask (docs/planning.md), so a surface beside its mask shows at once.
// Hand-written PLY reading: a few dozen lines for the two layouts the project writes, where a
// library (three.js's loader) would bring a whole renderer into the bundle. No DOM: unit-tested.
import type { M4, Volume } from "./nifti";

export interface Mesh { vertices: Float64Array; faces: Uint32Array } // xyz per vertex; 3 indices per triangle

const SIZES: Record<string, number> = { char: 1, uchar: 1, int8: 1, uint8: 1, short: 2, ushort: 2, int16: 2, uint16: 2, int: 4, uint: 4, int32: 4, uint32: 4, float: 4, float32: 4, double: 8, float64: 8 };
function reader(type: string, v: DataView, le: boolean): (o: number) => number {
  switch (type) {
    case "char": case "int8": return (o) => v.getInt8(o);
    case "uchar": case "uint8": return (o) => v.getUint8(o);
    case "short": case "int16": return (o) => v.getInt16(o, le);
    case "ushort": case "uint16": return (o) => v.getUint16(o, le);
    case "int": case "int32": return (o) => v.getInt32(o, le);
    case "uint": case "uint32": return (o) => v.getUint32(o, le);
    case "float": case "float32": return (o) => v.getFloat32(o, le);
    case "double": case "float64": return (o) => v.getFloat64(o, le);
    default: throw new Error(`PLY: unknown property type '${type}'`);
  }
}

/** Reads a PLY mesh (binary little/big endian or ASCII): vertices x, y, z and triangle faces
 *  (polygons fanned into triangles). Throws naming `name` and the problem. */
export function parsePly(buf: ArrayBuffer, name = "surface"): Mesh {
  const bytes = new Uint8Array(buf);
  const headText = new TextDecoder("latin1").decode(bytes.subarray(0, Math.min(bytes.length, 4096)));
  const end = headText.indexOf("end_header");
  if (!headText.startsWith("ply") || end < 0) throw new Error(`${name}: not a PLY file`);
  let bodyStart = end + "end_header".length;
  while (bodyStart < bytes.length && bytes[bodyStart] !== 0x0a) bodyStart++;
  bodyStart++;
  const lines = headText.slice(0, end).split(/\r?\n/).map((l) => l.trim().split(/\s+/));
  const format = lines.find((l) => l[0] === "format")?.[1] ?? "";
  if (!["ascii", "binary_little_endian", "binary_big_endian"].includes(format)) throw new Error(`${name}: PLY format '${format}' is not supported`);
  interface Prop { name: string; type: string; countType?: string }
  const elements: { name: string; count: number; props: Prop[] }[] = [];
  for (const l of lines) {
    if (l[0] === "element") elements.push({ name: l[1], count: Number(l[2]), props: [] });
    else if (l[0] === "property" && elements.length) {
      const e = elements[elements.length - 1];
      if (l[1] === "list") e.props.push({ name: l[4], type: l[3], countType: l[2] });
      else e.props.push({ name: l[2], type: l[1] });
    }
  }
  const vEl = elements.find((e) => e.name === "vertex"), fEl = elements.find((e) => e.name === "face");
  if (!vEl || !["x", "y", "z"].every((a) => vEl.props.some((p) => p.name === a))) throw new Error(`${name}: PLY has no vertex x, y, z`);
  const vertices = new Float64Array(3 * vEl.count);
  const faces: number[] = [];
  const pushPoly = (idx: number[]) => { for (let t = 1; t + 1 < idx.length; t++) faces.push(idx[0], idx[t], idx[t + 1]); };
  if (format === "ascii") {
    const tokens = new TextDecoder().decode(bytes.subarray(bodyStart)).split(/\s+/).filter(Boolean).map(Number);
    let p = 0;
    for (const e of elements)
      for (let n = 0; n < e.count; n++)
        for (const pr of e.props) {
          if (pr.countType) { const c = tokens[p++]; const idx = tokens.slice(p, p + c); p += c; if (e === fEl && pr.name.startsWith("vertex_ind")) pushPoly(idx); }
          else { const x = tokens[p++]; if (e === vEl) { const a = "xyz".indexOf(pr.name); if (a >= 0 && pr.name.length === 1) vertices[3 * n + a] = x; } }
        }
  } else {
    const le = format === "binary_little_endian";
    const view = new DataView(buf);
    let o = bodyStart;
    try {
    for (const e of elements) {
      const readers = e.props.map((pr) => ({ pr, r: reader(pr.type, view, le), rc: pr.countType ? reader(pr.countType, view, le) : null }));
      for (let n = 0; n < e.count; n++)
        for (const { pr, r, rc } of readers) {
          if (o > buf.byteLength) throw new Error(`${name}: PLY cut short`);
          if (rc) {
            const c = rc(o); o += SIZES[pr.countType!];
            const idx: number[] = [];
            for (let k = 0; k < c; k++) { idx.push(r(o)); o += SIZES[pr.type]; }
            if (e === fEl && pr.name.startsWith("vertex_ind")) pushPoly(idx);
          } else {
            const x = r(o); o += SIZES[pr.type];
            if (e === vEl && pr.name.length === 1) { const a = "xyz".indexOf(pr.name); if (a >= 0) vertices[3 * n + a] = x; }
          }
        }
    }
    } catch (e) {
      if (e instanceof RangeError) throw new Error(`${name}: PLY cut short`);
      throw e;
    }
    if (o > buf.byteLength) throw new Error(`${name}: PLY cut short`);
  }
  for (const f of faces) if (!(f >= 0 && f < vEl.count)) throw new Error(`${name}: a face names vertex ${f} of ${vEl.count}`);
  return { vertices, faces: Uint32Array.from(faces) };
}

/** A segment in a panel of the mask picture: u, v in [0, 1] as maskQuickCheck draws them. */
export type Seg = [number, number, number, number];

const apply = (m: M4, p: ArrayLike<number>): [number, number, number] =>
  [0, 1, 2].map((r) => m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]) as [number, number, number];

/**
 * The surface cut by the three planes of the mask picture (axial k = c2, coronal j = c1,
 * sagittal i = c0 in the mask's voxel indices, `centroid`), each segment in its panel's (u, v)
 * as `maskQuickCheck` maps voxels (u = (i + 0.5) / X across, v flipped so up is up); and the share
 * of the outline's length whose midpoint lies inside the mask or within 2 voxels of it (a mask
 * voxel in the 5x5 neighbourhood in the slice), 0..1.
 */
export function surfaceOutline(mesh: Mesh, mask: Volume, centroid: [number, number, number]): { panels: Seg[][]; inMask: number; lengthVox: number } {
  const [X, Y, Z] = mask.dims;
  const n = mesh.vertices.length / 3;
  const ijk = new Float64Array(3 * n);
  for (let v = 0; v < n; v++) ijk.set(apply(mask.lpsToIjk, mesh.vertices.subarray(3 * v, 3 * v + 3)), 3 * v);
  const inside = (i: number, j: number, k: number) => {
    const a = Math.round(i), b = Math.round(j), c = Math.round(k);
    return a >= 0 && b >= 0 && c >= 0 && a < X && b < Y && c < Z && mask.data[a + X * (b + Y * c)] > 0;
  };
  // Panel p: its normal axis, the two axes across and up, and their sizes.
  const spec: [number, number, number, number, number][] = [[2, 0, 1, X, Y], [1, 0, 2, X, Z], [0, 1, 2, Y, Z]];
  const panels: Seg[][] = [[], [], []];
  let len = 0, inLen = 0;
  spec.forEach(([ax, ua, va, US, VS], p) => {
    const plane = centroid[ax];
    for (let f = 0; f < mesh.faces.length; f += 3) {
      const pts: number[][] = [];
      for (let e = 0; e < 3; e++) {
        const a = 3 * mesh.faces[f + e], b = 3 * mesh.faces[f + (e + 1) % 3];
        const da = ijk[a + ax] - plane, db = ijk[b + ax] - plane;
        if ((da < 0 && db >= 0) || (da >= 0 && db < 0)) {
          const t = da / (da - db);
          pts.push([0, 1, 2].map((k) => ijk[a + k] + t * (ijk[b + k] - ijk[a + k])));
        }
      }
      if (pts.length !== 2) continue;
      const [P, Q] = pts;
      panels[p].push([(P[ua] + 0.5) / US, 1 - (P[va] + 0.5) / VS, (Q[ua] + 0.5) / US, 1 - (Q[va] + 0.5) / VS]);
      const l = Math.hypot(P[ua] - Q[ua], P[va] - Q[va]);
      const M = [0, 1, 2].map((k) => (P[k] + Q[k]) / 2);
      let near = false;
      for (let du = -2; du <= 2 && !near; du++) for (let dv = -2; dv <= 2 && !near; dv++) {
        const c = [...M];
        c[ua] += du; c[va] += dv; c[ax] = plane;
        near = inside(c[0], c[1], c[2]);
      }
      len += l;
      if (near) inLen += l;
    }
  });
  return { panels, inMask: len ? inLen / len : 0, lengthVox: len };
}
