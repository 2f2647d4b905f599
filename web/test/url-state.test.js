// The view state survives the URL: what stateToParams writes, paramsToState reads back, and what a hand-edited or
// stale URL holds is read as far as it makes sense.
import assert from "node:assert/strict";
import { describe, it } from "node:test";
import { DEFAULT_SIZE, ViewState } from "../src/viewer/state.js";
import { paramsToState, stateToParams } from "../src/viewer/url-state.js";

const FULL = {
  mode: "instance",
  size: 1.2, // 1.5 / 1.25: one "[" press
  hidden: [-1, 3, 12],
  sel: 7,
  q: "office chair & desk = 2 #1 ü",
  minScore: 0.25,
  cam: [1.25, -2.5, 3, 0, 0.001, -0.5],
  frame: "frame-007",
  photo: true,
};

// Through the string, as a reload reads it.
const roundTrip = (state) => paramsToState(new URLSearchParams(stateToParams(state).toString()));

describe("URL state", () => {
  it("round-trips every field", () => {
    assert.deepEqual(roundTrip(FULL), FULL);
  });

  it("writes only the mode for a default view", () => {
    const state = new ViewState().snapshot();
    assert.equal(stateToParams(state).toString(), "mode=semantic");
    assert.deepEqual(roundTrip(state), { mode: "semantic" });
  });

  it("reopens the photo view and the query's threshold, and leaves them out at their defaults", () => {
    const params = stateToParams({ ...FULL, minScore: 0.3, photo: true });
    assert.equal(params.get("photo"), "1");
    assert.equal(params.get("min"), "0.3");
    const plain = stateToParams({ ...FULL, minScore: 0.5, photo: false });
    assert.equal(plain.get("photo"), null);
    assert.equal(plain.get("min"), null);
    assert.equal(paramsToState(new URLSearchParams("min=7&photo=yes")).minScore, 1);
    assert.equal(paramsToState(new URLSearchParams("photo=yes")).photo, undefined);
  });

  it("keeps the size to three decimals", () => {
    const params = stateToParams({ ...FULL, size: 1.5 / 1.25 / 1.25 });
    assert.equal(params.get("size"), "0.960");
    assert.equal(paramsToState(params).size, 0.96);
  });

  it("drops what the state no longer has and keeps other parameters", () => {
    const params = new URLSearchParams("other=1&sel=4&q=rug&size=2.000&cam=1,2,3,4,5,6");
    stateToParams({ mode: "camera", size: DEFAULT_SIZE, hidden: [], sel: null, q: "", cam: null }, params);
    assert.equal(params.toString(), "other=1&mode=camera");
  });

  it("reads garbage as absent", () => {
    const state = paramsToState(new URLSearchParams("size=big&hidden=1,x,,2&cam=1,2,3,4,5&sel="));
    assert.deepEqual(state, { size: DEFAULT_SIZE, hidden: [1, 2] });
    assert.equal(paramsToState(new URLSearchParams("cam=1,2,3,4,5,nope")).cam, undefined);
    assert.equal(paramsToState(new URLSearchParams("cam=1,2,,4,5,6")).cam, undefined);
    assert.deepEqual(paramsToState(new URLSearchParams("sel=chair")), {});
    assert.deepEqual(paramsToState(new URLSearchParams("")), {});
  });

  it("leaves an unknown mode to the state, which falls back to semantic", () => {
    const store = new ViewState(paramsToState(new URLSearchParams("mode=xray&sel=3")));
    assert.equal(store.value.mode, "xray");
    assert.equal(store.setMode(store.value.mode), "semantic");
    assert.equal(store.value.sel, 3);
  });
});
