// The viewer's state owner, its key map and its read-outs: the rules behind the clicks and keys.
import assert from "node:assert/strict";
import { describe, it } from "node:test";
import {
  answerText,
  hitScoreText,
  hitsText,
  instanceOrder,
  instanceTitle,
  legendRows,
  medianScale,
  progressText,
  summaryText,
} from "../src/viewer/describe.js";
import { keyCommand } from "../src/viewer/keys.js";
import { MAX_SIZE, MIN_SIZE, ViewState, nextMode } from "../src/viewer/state.js";

describe("ViewState", () => {
  it("starts from the defaults under what the URL gave", () => {
    const store = new ViewState({ mode: "instance", sel: 4 });
    assert.deepEqual(store.snapshot(), {
      mode: "instance",
      size: 1.5,
      hidden: [],
      sel: 4,
      q: "",
      minScore: 0.5,
      cam: null,
      frame: null,
      photo: false,
    });
  });

  it("hands the host a copy, not the live state", () => {
    const seen = [];
    const store = new ViewState({}, (s) => seen.push(s));
    store.changed();
    store.setMode("camera");
    store.changed();
    assert.deepEqual(
      seen.map((s) => s.mode),
      ["semantic", "camera"],
    );
  });

  it("clamps the size and falls back to semantic for an unknown mode", () => {
    const store = new ViewState();
    assert.equal(store.setSize(1000), MAX_SIZE);
    assert.equal(store.setSize(0), MIN_SIZE);
    assert.equal(store.setMode("xray"), "semantic");
    assert.equal(nextMode("instance"), "camera");
    assert.equal(nextMode("camera"), "semantic");
  });

  it("keeps hidden classes sorted and unique", () => {
    const store = new ViewState();
    for (const index of [5, -1, 5, 2]) store.setClassVisible(index, false);
    store.setClassVisible(2, true);
    assert.deepEqual(store.value.hidden, [-1, 5]);
    assert.ok(store.isClassHidden(-1));
  });

  it("drops the query on a selection unless a hit was clicked", () => {
    const store = new ViewState();
    const hits = [{ instance_id: 3 }, { instance_id: 1 }];
    store.answer("chair", hits);
    assert.deepEqual([store.value.q, store.value.sel, [...store.lit]], ["chair", null, [3, 1]]);
    store.select(1, true);
    assert.deepEqual([store.value.q, store.value.sel, [...store.lit], store.hits], ["chair", 1, [1], hits]);
    store.select(null);
    assert.deepEqual([store.value.q, store.value.sel, store.lit.size, store.hits], ["", null, 0, []]);
  });

  it("draws the previewed instance's box, else the lit ones'", () => {
    const store = new ViewState();
    store.answer("chair", [{ instance_id: 3 }, { instance_id: 1 }]);
    assert.deepEqual(store.boxed(), [3, 1]);
    store.setHover(8);
    assert.deepEqual(store.boxed(), [8]);
    store.setHover(null);
    assert.deepEqual(store.boxed(), [3, 1]);
  });

  it("keeps the threshold in [0, 1] and the photo view as a flag", () => {
    const store = new ViewState();
    assert.equal(store.setMinScore("0.25"), 0.25);
    assert.equal(store.setMinScore(3), 1);
    assert.equal(store.setMinScore(-1), 0);
    assert.equal(store.setMinScore("x"), 0.5);
    store.setPhoto(1);
    assert.equal(store.snapshot().photo, true);
    store.setFrame(12);
    assert.equal(store.value.frame, "12");
    store.setFrame("");
    assert.equal(store.value.frame, null);
  });

  it("keeps the camera to the millimetre", () => {
    const store = new ViewState();
    store.setCamera([1.23456, -0.0004, 2, 0, 0, 0.9996]);
    assert.deepEqual(store.value.cam, [1.235, -0, 2, 0, 0, 1]);
  });
});

describe("keyCommand", () => {
  it("maps the shortcuts of the help", () => {
    const map = Object.fromEntries(
      ["1", "2", "3", "m", "p", "f", "[", "]", "/", "?", "Escape"].map((key) => [key, keyCommand({ key })]),
    );
    assert.deepEqual(map, {
      1: "mode:camera",
      2: "mode:semantic",
      3: "mode:instance",
      m: "mode:next",
      p: "photo",
      f: "fit",
      "[": "smaller",
      "]": "larger",
      "/": "query",
      "?": "help",
      Escape: "escape",
    });
  });

  it("leaves other keys and the browser's shortcuts alone", () => {
    assert.equal(keyCommand({ key: "x" }), null);
    assert.equal(keyCommand({ key: "toString" }), null);
    assert.equal(keyCommand({ key: "f", ctrlKey: true }), null);
    assert.equal(keyCommand({ key: "1", metaKey: true }), null);
    assert.equal(keyCommand({ key: "m", altKey: true }), null);
  });
});

describe("read-outs", () => {
  const header = {
    count: 1000,
    total: 25000,
    title: "room",
    classes: [
      { index: 0, name: "wall", kind: "stuff", color: [1, 1, 1], count: 700 },
      { index: 1, name: "lamp", kind: "thing", color: [2, 2, 2], count: 0 },
      { index: 2, name: "chair", kind: "thing", color: [3, 3, 3], count: 200 },
    ],
    void: { color: [128, 128, 128], count: 100 },
    instances: [
      { id: 4, class_name: "wall" },
      { id: 2, class_name: "chair" },
      { id: 1, class_name: "wall" },
    ],
  };

  it("lists the classes that have primitives, then void", () => {
    assert.deepEqual(
      legendRows(header).map((r) => [r.index, r.name]),
      [
        [0, "wall"],
        [2, "chair"],
        [-1, "(void)"],
      ],
    );
    assert.deepEqual(legendRows({ ...header, void: { color: [0, 0, 0], count: 0 } }).length, 2);
  });

  it("orders instances by class name, then id", () => {
    assert.deepEqual(
      instanceOrder(header.instances).map((i) => i.id),
      [2, 1, 4],
    );
    assert.deepEqual(
      header.instances.map((i) => i.id),
      [4, 2, 1],
      "the header is left as it was",
    );
  });

  it("says what was decimated, how far loading is, how many hits", () => {
    assert.equal(summaryText(header), "room: 1,000 primitives (of 25,000, decimated), 3 instances");
    assert.equal(summaryText({ ...header, title: "", total: 1000 }), "1,000 primitives, 3 instances");
    assert.equal(progressText(2.5e6, 1e7), "Loading scene 25% (2.5 of 10.0 MB)");
    assert.equal(progressText(2.5e6, 0), "Loading scene (2.5 MB)");
    assert.equal(hitsText(1, "rug"), '1 hit for "rug"');
    assert.equal(hitsText(0, "rug"), '0 hits for "rug"');
    assert.equal(
      instanceTitle({ num_points: 12, bbox_min: [0, 0, 0], bbox_max: [1, 0.5, 2.125] }),
      "12 primitives, box 1.00×0.50×2.13 m",
    );
  });

  it("says when nothing passed the threshold and the closest are listed below it", () => {
    const hit = { instance_id: 1, score: 0.42 };
    assert.equal(
      answerText("sofa", { hits: [hit], candidates: [], min_score: 0.3 }),
      '1 hit for "sofa" (score ≥ 0.30)',
    );
    assert.equal(
      answerText("a place for books", { hits: [], candidates: [hit], min_score: 0.5 }),
      'no instance scored ≥ 0.50 for "a place for books"; the closest, below it (lower the threshold to light them):',
    );
    assert.equal(answerText("rug", { hits: [], candidates: [], min_score: 0.5 }), '0 hits for "rug" (score ≥ 0.50)');
    assert.equal(answerText("rug", { hits: [] }), '0 hits for "rug" (score ≥ 0.50)', "an older server's answer");
  });

  it("shows a hit's score in three decimals, or its first digits when three decimals read 0.000", () => {
    assert.deepEqual([0.8123, 0.0005, 0, 1].map(hitScoreText), ["0.812", "0.001", "0.000", "1.000"]);
    const nearZero = [3.0004e-5, 5.48e-6, 5.36e-6].map(hitScoreText);
    assert.deepEqual(nearZero, ["3.0e-5", "5.5e-6", "5.4e-6"]); // ranked, not three ties
    assert.deepEqual(nearZero.map(Number), [3.0e-5, 5.5e-6, 5.4e-6]);
  });

  it("takes the median radius from a sample", () => {
    assert.equal(medianScale(new Float32Array([0.5, 0.1, 0.3])), new Float32Array([0.3])[0]);
    assert.equal(medianScale(new Float32Array(0)), 0.01);
    const many = Float32Array.from({ length: 100000 }, (_, i) => ((i * 7919) % 100000) / 100000); // shuffled 0..1
    assert.ok(Math.abs(medianScale(many) - 0.5) <= 0.01);
  });
});
