// The first view of a capture: from behind its cameras, looking the way they looked. A phone capture of a door
// seen from a fixed direction about the up axis can show the door edge-on; the capture's own cameras say which
// side of the scene a person looked at. Pure: arrays in, arrays out (node --test covers it).

// The cameras' headings must agree this much (length of the mean of their unit horizontal headings, 0..1) to pick
// the view: a capture that walks around its scene (a room, an object) looks every way and has no side to pick.
export const MIN_AGREEMENT = 0.5;
// The first view looks down at least this much (the floor and the tops of things show), and at most this much.
export const MIN_ELEVATION_DEG = 20;
export const MAX_ELEVATION_DEG = 60;

const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const scaled = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const minus = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const length = (a) => Math.sqrt(dot(a, a));

function unit(a) {
  const n = length(a);
  return Number.isFinite(n) && n > 1e-9 ? scaled(a, 1 / n) : null;
}

// The viewing direction (the OpenCV camera's +z, the third column) of a 4x4 T_world_cam; null when unreadable.
function forwardOf(pose) {
  if (!Array.isArray(pose) || pose.length < 3 || !pose.slice(0, 3).every((row) => Array.isArray(row))) return null;
  const forward = [pose[0][2], pose[1][2], pose[2][2]];
  return forward.every(Number.isFinite) ? unit(forward) : null;
}

// frames: cameras.json's frames ([{T_world_cam}]); up: the run's up ([x, y, z]).
// Returns the unit direction from the scene's centre to the first view's camera, or null where the cameras pick no
// side (none, or headings that disagree): the viewer then keeps its fixed direction. The camera looks along the
// cameras' mean horizontal heading, tilted down by their mean pitch held within MIN..MAX_ELEVATION_DEG.
export function captureViewDirection(frames, up) {
  const u = Array.isArray(up) && up.length === 3 ? unit(up) : null;
  if (!u || !Array.isArray(frames)) return null;
  let sum = [0, 0, 0];
  let sinPitch = 0;
  let count = 0;
  for (const frame of frames) {
    const forward = forwardOf(frame?.T_world_cam);
    if (!forward) continue;
    const vertical = dot(forward, u);
    const heading = unit(minus(forward, scaled(u, vertical)));
    if (!heading) continue; // straight up or down: no heading
    sum = [sum[0] + heading[0], sum[1] + heading[1], sum[2] + heading[2]];
    sinPitch += vertical;
    count += 1;
  }
  if (count === 0) return null;
  const mean = scaled(sum, 1 / count);
  if (length(mean) < MIN_AGREEMENT) return null;
  const heading = unit(mean);
  const downDeg = (Math.asin(Math.max(-1, Math.min(1, -sinPitch / count))) * 180) / Math.PI;
  const elevation = (Math.max(MIN_ELEVATION_DEG, Math.min(MAX_ELEVATION_DEG, downDeg)) * Math.PI) / 180;
  // Behind the cameras (against their heading) and above (along up): the camera then looks along the heading.
  return unit(minus(scaled(u, Math.sin(elevation)), scaled(heading, Math.cos(elevation))));
}
