// The one owner of the viewer's state. `value` is what the URL keeps (mode, size, hidden classes, selection, query,
// the query's threshold, camera, the capture frame looked from, photo on); `lit`, `hover` and `hits` are what is shown now and never leave the page. No DOM, no three.js.

export const MODES = ["camera", "semantic", "instance"];
export const DEFAULT_MODE = "semantic";
export const DEFAULT_SIZE = 1.5; // primitives are drawn a little larger than their radius: surfaces read closed
export const SIZE_STEP = 1.25;
export const MIN_SIZE = 1 / 16;
export const MAX_SIZE = 16;
// A query's hits score at least this by default: the query beats the vocabulary's other classes together (the
// server's default; panogs_core/language/query.py). The viewer's threshold control starts here.
export const DEFAULT_MIN_SCORE = 0.5;

export function clampMinScore(value) {
  const number = Number(value);
  return Number.isFinite(number) ? Math.min(1, Math.max(0, number)) : DEFAULT_MIN_SCORE;
}

export function normaliseMode(mode) {
  return MODES.includes(mode) ? mode : DEFAULT_MODE;
}

export function nextMode(mode) {
  return MODES[(MODES.indexOf(mode) + 1) % MODES.length];
}

export function clampSize(size) {
  return Math.min(MAX_SIZE, Math.max(MIN_SIZE, size));
}

// Camera position and target to the millimetre: short URLs, and a reload lands where the user left.
export function roundCamera(numbers) {
  return numbers.map((v) => Number(v.toFixed(3)));
}

export class ViewState {
  // initial: a partial state (from the URL); onChange(snapshot): told when the host should save the state
  constructor(initial = {}, onChange = null) {
    this.value = {
      mode: DEFAULT_MODE,
      size: DEFAULT_SIZE,
      hidden: [],
      sel: null,
      q: "",
      minScore: DEFAULT_MIN_SCORE,
      cam: null,
      frame: null,
      photo: false,
      ...initial,
    };
    this.onChange = onChange;
    this.lit = new Set(); // instances lit by the selection or the query's hits
    this.hover = null; // an instance previewed from a list (the pointer is on its row): its box is drawn
    this.hits = [];
  }

  snapshot() {
    return { ...this.value };
  }

  changed() {
    if (this.onChange) this.onChange(this.snapshot());
  }

  setMode(mode) {
    this.value.mode = normaliseMode(mode);
    return this.value.mode;
  }

  setSize(size) {
    this.value.size = clampSize(size);
    return this.value.size;
  }

  setClassVisible(index, visible) {
    const hidden = new Set(this.value.hidden);
    if (visible) hidden.delete(index);
    else hidden.add(index);
    this.value.hidden = [...hidden].sort((a, b) => a - b);
  }

  isClassHidden(index) {
    return this.value.hidden.includes(index);
  }

  // One instance selected (null: none). Unless the query is kept (a click on one of its hits), it is dropped.
  select(id, keepQuery = false) {
    this.value.sel = id;
    if (!keepQuery) {
      this.hits = [];
      this.value.q = "";
    }
    this.lit = new Set(id === null ? [] : [id]);
  }

  // A query's answer: its hits are lit, in the server's order, and the selection is dropped.
  answer(text, hits) {
    this.value.q = text;
    this.value.sel = null;
    this.hits = hits;
    this.lit = new Set(hits.map((hit) => hit.instance_id));
  }

  setMinScore(value) {
    this.value.minScore = clampMinScore(value);
    return this.value.minScore;
  }

  // The capture frame the camera looks from (its id as text), or null once the view moves.
  setFrame(id) {
    this.value.frame = id === null || id === undefined || id === "" ? null : String(id);
  }

  setPhoto(on) {
    this.value.photo = Boolean(on);
  }

  setHover(id) {
    this.hover = id;
  }

  // The instances whose boxes are drawn: the previewed one, else the lit ones.
  boxed() {
    return this.hover !== null ? [this.hover] : [...this.lit];
  }

  setCamera(numbers) {
    this.value.cam = roundCamera(numbers);
  }
}
