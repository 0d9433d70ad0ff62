import { describe, expect, it } from "vitest";
import { parsePly, surfaceOutline, type Mesh } from "../src/surface_outline";
import type { Volume } from "../src/nifti";

/** A UV sphere of radius r about c (world = voxel indices here). */
function sphere(c: number[], r: number, nu = 48, nv = 24): { v: number[][]; f: number[][] } {
  const v: number[][] = [], f: number[][] = [];
  for (let a = 0; a <= nv; a++) for (let b = 0; b < nu; b++) {
    const th = (Math.PI * a) / nv, ph = (2 * Math.PI * b) / nu;
    v.push([c[0] + r * Math.sin(th) * Math.cos(ph), c[1] + r * Math.sin(th) * Math.sin(ph), c[2] + r * Math.cos(th)]);
  }
  for (let a = 0; a < nv; a++) for (let b = 0; b < nu; b++) {
    const i = a * nu + b, j = a * nu + (b + 1) % nu;
    f.push([i, j, j + nu, i + nu]); // quads: the reader fans them into triangles
  }
  return { v, f };
}

/** Binary little-endian PLY as VTK writes it (float xyz, float normals, uchar/int lists). */
function binaryPly(s: { v: number[][]; f: number[][] }, cut = 0): ArrayBuffer {
  const head = `ply\nformat binary_little_endian 1.0\ncomment SPACE=LPS\nelement vertex ${s.v.length}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face ${s.f.length}\nproperty list uchar int vertex_indices\nend_header\n`;
  const hb = new TextEncoder().encode(head);
  const size = hb.length + s.v.length * 24 + s.f.reduce((t, f) => t + 1 + 4 * f.length, 0);
  const buf = new ArrayBuffer(size), dv = new DataView(buf);
  new Uint8Array(buf).set(hb);
  let o = hb.length;
  for (const p of s.v) { for (const x of [...p, 0, 0, 1]) { dv.setFloat32(o, x, true); o += 4; } }
  for (const f of s.f) { dv.setUint8(o++, f.length); for (const i of f) { dv.setInt32(o, i, true); o += 4; } }
  return cut ? buf.slice(0, size - cut) : buf;
}

const I4 = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];
function ballMask(c: number[], r: number, n = 40): Volume {
  const data = new Uint8Array(n * n * n);
  for (let k = 0; k < n; k++) for (let j = 0; j < n; j++) for (let i = 0; i < n; i++)
    data[i + n * (j + n * k)] = Math.hypot(i - c[0], j - c[1], k - c[2]) <= r ? 1 : 0;
  return { dims: [n, n, n], spacing: [1, 1, 1], data, ijkToLps: I4, lpsToIjk: I4 };
}

describe("surface outline on the mask check", () => {
  const s = sphere([20, 20, 20], 10);
  it("reads the binary and the ASCII PLY alike, and refuses a cut one", () => {
    const m = parsePly(binaryPly(s), "brain_surface.ply");
    expect(m.vertices.length).toBe(3 * s.v.length);
    expect(m.faces.length).toBe(3 * 2 * s.f.length);
    expect(m.vertices[3 * 5 + 2]).toBeCloseTo(s.v[5][2], 4);
    const ascii = `ply\nformat ascii 1.0\nelement vertex ${s.v.length}\nproperty float x\nproperty float y\nproperty float z\nelement face ${s.f.length}\nproperty list uchar int vertex_indices\nend_header\n` +
      s.v.map((p) => p.join(" ")).join("\n") + "\n" + s.f.map((f) => `${f.length} ${f.join(" ")}`).join("\n") + "\n";
    const a = parsePly(new TextEncoder().encode(ascii).buffer as ArrayBuffer);
    expect(Array.from(a.faces)).toEqual(Array.from(m.faces));
    expect(() => parsePly(binaryPly(s, 7), "brain_surface.ply")).toThrow(/brain_surface.ply: PLY cut short/);
    expect(() => parsePly(new TextEncoder().encode("solid stl\n").buffer as ArrayBuffer, "x.stl")).toThrow(/x.stl: not a PLY file/);
  });

  it("cuts the surface by the three slices and tells a surface inside its mask from one beside it", () => {
    const mesh: Mesh = parsePly(binaryPly(s));
    const mask = ballMask([20, 20, 20], 10);
    const o = surfaceOutline(mesh, mask, [20, 20, 20]);
    for (const panel of o.panels) {
      expect(panel.length).toBeGreaterThan(40);
      // Every endpoint on the circle of radius 10 about the centre (panel units back to voxels).
      for (const [u1, v1] of panel) expect(Math.hypot(u1 * 40 - 0.5 - 20, (1 - v1) * 40 - 0.5 - 20)).toBeGreaterThan(9.7);
      for (const [u1, v1] of panel) expect(Math.hypot(u1 * 40 - 0.5 - 20, (1 - v1) * 40 - 0.5 - 20)).toBeLessThan(10.01);
    }
    expect(o.inMask).toBeGreaterThan(0.99);
    expect(o.lengthVox).toBeGreaterThan(3 * 2 * Math.PI * 10 * 0.95);
    // A surface 6 voxels beside its mask: about half of its outline out of the mask (by the
    // geometry of two circles of radius 10, 6 apart, with 2 voxels of slack: 52 %).
    const shifted = parsePly(binaryPly(sphere([26, 20, 20], 10)));
    expect(surfaceOutline(shifted, mask, [20, 20, 20]).inMask).toBeLessThan(0.75);
  });
});
