// Colour rules: which colour each primitive gets in each mode, and which flag (hidden, dimmed, lit) it gets from
// the hidden classes and the lit instances.
import assert from "node:assert/strict";
import { describe, it } from "node:test";
import { FLAG, classTable, cssRgb, flagPoints, instanceTable, paintPoints } from "../src/viewer/colours.js";

const VOID = [128, 128, 128];
const WALL = [31, 119, 180];
const CHAIR = [255, 127, 14];
const header = {
  classes: [
    { index: 0, name: "wall", color: WALL },
    { index: 1, name: "chair", color: CHAIR },
  ],
  void: { color: VOID },
  instances: [
    { id: 0, color: [1, 2, 3] },
    { id: 2, color: [7, 8, 9] }, // ids may skip: id 1 has no instance
  ],
};
// Five primitives: void, wall, chair, a class index past the vocabulary, chair again.
const scene = {
  header,
  color: new Uint8Array([10, 11, 12, 20, 21, 22, 30, 31, 32, 40, 41, 42, 50, 51, 52]),
  semantic: new Int16Array([-1, 0, 1, 9, 1]),
  instance: new Int32Array([-1, 0, 2, 1, 7]),
};
const rows = (rgb) => Array.from({ length: rgb.length / 3 }, (_, i) => [...rgb.subarray(i * 3, i * 3 + 3)]);

describe("colour tables", () => {
  it("puts void first, then the classes in vocabulary order", () => {
    assert.deepEqual(rows(classTable(header.classes, VOID)), [VOID, WALL, CHAIR]);
  });

  it("puts each instance at its id, void where no instance has the id", () => {
    assert.deepEqual(rows(instanceTable(header.instances, VOID)), [[1, 2, 3], VOID, [7, 8, 9]]);
  });

  it("writes CSS colours the CSSOM takes", () => {
    assert.equal(cssRgb([31, 119, 180]), "rgb(31, 119, 180)");
  });
});

describe("paintPoints", () => {
  const paint = (mode) => rows(paintPoints(mode, scene, new Uint8Array(15)));

  it("camera: the primitive's own colour", () => {
    assert.deepEqual(paint("camera"), rows(scene.color));
  });

  it("semantic: the class's palette colour, void for -1 and for an index past the vocabulary", () => {
    assert.deepEqual(paint("semantic"), [VOID, WALL, CHAIR, VOID, CHAIR]);
  });

  it("instance: the instance's colour, void for -1 and for an id no instance has", () => {
    // id 1 is inside the table (ids skip), id 7 past it.
    assert.deepEqual(paint("instance"), [VOID, [1, 2, 3], [7, 8, 9], VOID, VOID]);
  });

  it("overwrites the previous mode's colours completely", () => {
    const out = paintPoints("camera", scene, new Uint8Array(15));
    paintPoints("semantic", scene, out);
    assert.deepEqual(rows(out), [VOID, WALL, CHAIR, VOID, CHAIR]);
  });
});

describe("flagPoints", () => {
  const flags = (hidden, lit) => [
    ...flagPoints(scene.semantic, scene.instance, 2, hidden, new Set(lit), new Uint8Array(5)),
  ];

  it("leaves every primitive normal when nothing is hidden or lit", () => {
    assert.deepEqual(flags([], []), Array(5).fill(FLAG.NORMAL));
  });

  it("lights the lit instances and dims the rest", () => {
    assert.deepEqual(flags([], [2]), [FLAG.DIM, FLAG.DIM, FLAG.LIT, FLAG.DIM, FLAG.DIM]);
  });

  it("hides a hidden class's primitives, lit or not; -1 hides void", () => {
    assert.deepEqual(flags([1], [2]), [FLAG.DIM, FLAG.DIM, FLAG.HIDDEN, FLAG.DIM, FLAG.HIDDEN]);
    assert.deepEqual(flags([-1], []), [FLAG.HIDDEN, FLAG.NORMAL, FLAG.NORMAL, FLAG.NORMAL, FLAG.NORMAL]);
  });

  it("ignores hidden indices outside the vocabulary", () => {
    assert.deepEqual(flags([2, 9, -2], []), Array(5).fill(FLAG.NORMAL));
  });
});
