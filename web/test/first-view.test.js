// The first view of a capture looks the way its cameras looked, from behind and above them; cameras that look every
// way (a walk around a room) or none leave the viewer's fixed direction (null).
import assert from "node:assert/strict";
import { describe, it } from "node:test";
import { MAX_ELEVATION_DEG, MIN_ELEVATION_DEG, captureViewDirection } from "../src/viewer/first-view.js";

const deg = (rad) => (rad * 180) / Math.PI;
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];

// A camera-to-world pose (OpenCV axes) whose forward axis (third column) is `forward`; the other columns are
// left as zeros: only the forward axis is read.
function poseLooking(forward, at = [0, 0, 0]) {
  return [
    [0, 0, forward[0], at[0]],
    [0, 0, forward[1], at[1]],
    [0, 0, forward[2], at[2]],
    [0, 0, 0, 1],
  ];
}

const frame = (forward, at) => ({ id: "f", T_world_cam: poseLooking(forward, at) });

// The horizontal heading the first view's camera looks along (minus the direction, flattened) and its downward
// pitch in degrees, for the run's up.
function viewOf(direction, up) {
  const look = direction.map((v) => -v);
  const vertical = dot(look, up);
  const heading = look.map((v, i) => v - vertical * up[i]);
  const n = Math.hypot(...heading);
  return { heading: heading.map((v) => v / n), down: deg(Math.asin(-vertical)) };
}

describe("captureViewDirection", () => {
  it("looks along the cameras' mean heading in a z-up world", () => {
    // Cameras at eye level looking along -x, 10 degrees down, with a little spread either side.
    const s = Math.sin((10 * Math.PI) / 180);
    const frames = [-0.2, 0, 0.2].map((y) => frame([-1, y, -s], [3, y, 1.5]));
    const direction = captureViewDirection(frames, [0, 0, 1]);
    assert.ok(Math.abs(Math.hypot(...direction) - 1) < 1e-9);
    const { heading, down } = viewOf(direction, [0, 0, 1]);
    assert.ok(dot(heading, [-1, 0, 0]) > 0.9999, `heading ${heading}`);
    assert.ok(Math.abs(down - MIN_ELEVATION_DEG) < 1e-9, `a level capture is seen from ${MIN_ELEVATION_DEG} deg up`);
    assert.ok(direction[0] > 0, "the camera stands behind the capture's cameras (+x of the scene)");
  });

  it("turns with the run's up (a y-up capture, Record3D's)", () => {
    const up = [0, 1, 0];
    const frames = [frame([0.1, -0.6, -0.8]), frame([-0.1, -0.6, -0.8])];
    const { heading, down } = viewOf(captureViewDirection(frames, up), up);
    assert.ok(dot(heading, [0, 0, -1]) > 0.9999, `heading ${heading}`);
    assert.ok(Math.abs(down - deg(Math.asin(0.6))) < 0.5, `the cameras' own pitch (37 deg), got ${down}`);
  });

  it("holds the pitch between its bounds", () => {
    const steep = captureViewDirection([frame([0.05, 0, -1])], [0, 0, 1]);
    assert.ok(Math.abs(viewOf(steep, [0, 0, 1]).down - MAX_ELEVATION_DEG) < 1e-9);
    const upwards = captureViewDirection([frame([1, 0, 0.5])], [0, 0, 1]);
    assert.ok(Math.abs(viewOf(upwards, [0, 0, 1]).down - MIN_ELEVATION_DEG) < 1e-9);
  });

  it("picks no side for cameras that look every way, or for none", () => {
    const around = [0, 90, 180, 270].map((a) =>
      frame([Math.cos((a * Math.PI) / 180), Math.sin((a * Math.PI) / 180), -0.3]),
    );
    assert.equal(captureViewDirection(around, [0, 0, 1]), null);
    assert.equal(captureViewDirection([], [0, 0, 1]), null);
    assert.equal(captureViewDirection(undefined, [0, 0, 1]), null);
    assert.equal(captureViewDirection([frame([0, 0, -1])], [0, 0, 1]), null, "straight down has no heading");
    assert.equal(captureViewDirection([frame([1, 0, 0])], [0, 0, 0]), null, "no up");
  });

  it("skips frames it cannot read", () => {
    const frames = [{ id: "x" }, { id: "y", T_world_cam: [[1, 2]] }, { T_world_cam: poseLooking([NaN, 0, 0]) }];
    assert.equal(captureViewDirection(frames, [0, 0, 1]), null);
    const { heading } = viewOf(captureViewDirection([...frames, frame([0, 1, 0])], [0, 0, 1]), [0, 0, 1]);
    assert.ok(dot(heading, [0, 1, 0]) > 0.9999);
  });
});
