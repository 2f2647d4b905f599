// The view state <-> URL parameters (mode, size, hidden classes, selection, query and its threshold, camera, capture frame, photo): the app keeps them after
// `#/jobs/<id>?`, `panogs view` and the offline file after `#`. A parameter at its default is left out.
import { DEFAULT_MIN_SCORE, DEFAULT_SIZE, clampMinScore } from "./state.js";

export function stateToParams(state, params = new URLSearchParams()) {
  params.set("mode", state.mode);
  if (state.size !== DEFAULT_SIZE) params.set("size", state.size.toFixed(3));
  else params.delete("size");
  const optional = [
    ["hidden", state.hidden.join(",")],
    ["sel", state.sel ?? ""],
    ["q", state.q],
    ["min", state.minScore === undefined || state.minScore === DEFAULT_MIN_SCORE ? "" : String(state.minScore)],
    ["cam", state.cam ? state.cam.join(",") : ""],
    ["frame", state.frame ?? ""],
    ["photo", state.photo ? "1" : ""],
  ];
  for (const [key, value] of optional) {
    if (value === "" || value === null) params.delete(key);
    else params.set(key, value);
  }
  return params;
}

// "1,2,,x" -> [1, 2, NaN, NaN]: an empty entry is no number (Number("") would be 0).
const numbers = (text) => text.split(",").map((part) => (part.trim() === "" ? NaN : Number(part)));

// Only the parameters present and readable; the viewer fills in the rest (an unknown mode becomes the default).
export function paramsToState(params) {
  const state = {};
  if (params.get("mode")) state.mode = params.get("mode");
  if (params.get("size")) state.size = Number(params.get("size")) || DEFAULT_SIZE;
  if (params.get("hidden")) state.hidden = numbers(params.get("hidden")).filter(Number.isFinite);
  const sel = params.get("sel") ? Number(params.get("sel")) : NaN;
  if (Number.isInteger(sel)) state.sel = sel;
  if (params.get("q")) state.q = params.get("q");
  if (params.get("min")) state.minScore = clampMinScore(params.get("min"));
  if (params.get("photo") === "1") state.photo = true;
  if (params.get("frame")) state.frame = params.get("frame");
  const cam = numbers(params.get("cam") || "");
  if (cam.length === 6 && cam.every(Number.isFinite)) state.cam = cam;
  return state;
}
