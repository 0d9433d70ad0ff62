// Free orbit about the volume's centre (GET /api/render/volume): azimuth, elevation and distance
// turned into the camera pose POST /api/render takes (T_camera_from_world, OpenCV camera: x right,
// y down the image, z forward), built like core's look_at (core/src/pose.cpp).
// LPS mm: +x left, +y posterior, +z superior. Azimuth 0 looks from the left, -90 from the front
// (anterior), 90 from behind; elevation +90 from above.

export type Vec3 = [number, number, number];
export interface Orbit { azimuthDeg: number; elevationDeg: number; distanceMm: number }

const D2R = Math.PI / 180;
const sub = (a: Vec3, b: Vec3): Vec3 => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const cross = (a: Vec3, b: Vec3): Vec3 => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const dot = (a: Vec3, b: Vec3) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const norm = (a: Vec3): Vec3 => { const l = Math.hypot(...a); return [a[0] / l, a[1] / l, a[2] / l]; };

export const ELEVATION_LIMIT_DEG = 89;
export const DISTANCE_RANGE_MM: [number, number] = [150, 1500];

/** The six standard views as orbits (superior/inferior at the elevation limit). */
export const NAMED_VIEWS: Record<string, { azimuthDeg: number; elevationDeg: number }> = {
  left: { azimuthDeg: 0, elevationDeg: 0 }, anterior: { azimuthDeg: -90, elevationDeg: 0 },
  right: { azimuthDeg: 180, elevationDeg: 0 }, posterior: { azimuthDeg: 90, elevationDeg: 0 },
  superior: { azimuthDeg: -90, elevationDeg: ELEVATION_LIMIT_DEG }, inferior: { azimuthDeg: -90, elevationDeg: -ELEVATION_LIMIT_DEG },
};

/** The named view this orbit shows (within 0.5 degrees), or null. */
export function namedViewOf(o: Orbit): string | null {
  for (const [name, v] of Object.entries(NAMED_VIEWS)) {
    const da = ((((o.azimuthDeg - v.azimuthDeg) % 360) + 540) % 360) - 180;
    if (Math.abs(o.elevationDeg - v.elevationDeg) < 0.5 && (Math.abs(da) < 0.5 || Math.abs(v.elevationDeg) >= ELEVATION_LIMIT_DEG)) return name;
  }
  return null;
}

/** T_camera_from_world (4x4 rows) of a camera at `eye` looking at `target`, `up` up in the image. */
export function lookAt(eye: Vec3, target: Vec3, up: Vec3): number[][] {
  const z = norm(sub(target, eye));
  const x = norm(cross([-up[0], -up[1], -up[2]], z)); // image right: y (down) x z
  const y = cross(z, x);
  const t = [-dot(x, eye), -dot(y, eye), -dot(z, eye)];
  return [[...x, t[0]], [...y, t[1]], [...z, t[2]], [0, 0, 0, 1]];
}

/** The camera's position for an orbit about `target`. */
export function orbitEye(o: Orbit, target: Vec3): Vec3 {
  const a = o.azimuthDeg * D2R, e = o.elevationDeg * D2R;
  return [target[0] + o.distanceMm * Math.cos(e) * Math.cos(a), target[1] + o.distanceMm * Math.cos(e) * Math.sin(a),
          target[2] + o.distanceMm * Math.sin(e)];
}

/** The pose of an orbit: the image's up is the head's superior direction tilted with the
 *  elevation (continuous over the whole sphere; no flip at the poles within the limit). */
export function orbitPose(o: Orbit, target: Vec3): number[][] {
  const a = o.azimuthDeg * D2R, e = o.elevationDeg * D2R;
  const up: Vec3 = [-Math.sin(e) * Math.cos(a), -Math.sin(e) * Math.sin(a), Math.cos(e)];
  return lookAt(orbitEye(o, target), target, up);
}

/** A drag of (dx, dy) CSS px from `start`: sideways turns about the vertical axis, up/down tilts
 *  (clamped); `degPerPx` degrees a pixel. Dragging right brings the front into view from the left. */
export function dragOrbit(start: Orbit, dx: number, dy: number, degPerPx = 0.4): Orbit {
  let az = start.azimuthDeg - dx * degPerPx;
  az = ((((az + 180) % 360) + 360) % 360) - 180;
  const el = Math.max(-ELEVATION_LIMIT_DEG, Math.min(ELEVATION_LIMIT_DEG, start.elevationDeg + dy * degPerPx));
  return { azimuthDeg: az, elevationDeg: el, distanceMm: start.distanceMm };
}

/** Pinch: the distance divided by the fingers' spread ratio, within DISTANCE_RANGE_MM. */
export function zoomOrbit(start: Orbit, spreadRatio: number): Orbit {
  const r = Number.isFinite(spreadRatio) && spreadRatio > 0 ? spreadRatio : 1;
  const d = Math.max(DISTANCE_RANGE_MM[0], Math.min(DISTANCE_RANGE_MM[1], start.distanceMm / r));
  return { ...start, distanceMm: d };
}
