// Colour rules of the points: each mode's colour per primitive, and the flag that hides, dims or lights it (the
// vertex shader in points-layer.js reads the flag). Colours are RGB bytes; the palettes come from the scene's
// header (service/viewer/scene.py takes them from panogs_core/palette.py). No DOM, no three.js.

export const FLAG = { NORMAL: 0, DIM: 1, HIDDEN: 2, LIT: 3 };

export function cssRgb(rgb) {
  return `rgb(${rgb[0]}, ${rgb[1]}, ${rgb[2]})`;
}

// Class k's colour at (k + 1) * 3, void (-1) at 0.
export function classTable(classes, voidColor) {
  const table = new Uint8Array((classes.length + 1) * 3);
  table.set(voidColor, 0);
  classes.forEach((c, i) => table.set(c.color, (i + 1) * 3));
  return table;
}

// Instance id k's colour at k * 3 (ids are dense per run, so the table stays small); an id no instance has
// takes the void colour.
export function instanceTable(instances, voidColor) {
  let maxId = 0;
  for (const inst of instances) maxId = Math.max(maxId, inst.id);
  const table = new Uint8Array((maxId + 1) * 3);
  for (let id = 0; id <= maxId; id++) table.set(voidColor, id * 3);
  for (const inst of instances) table.set(inst.color, inst.id * 3);
  return table;
}

// out[i] = table entry of labels[i] + shift; a label outside the table takes the void colour.
function paintLabels(out, labels, shift, table, voidColor) {
  for (let i = 0; i < labels.length; i++) {
    const k = (labels[i] + shift) * 3;
    if (k < 0 || k >= table.length) {
      out.set(voidColor, i * 3);
    } else {
      out[i * 3] = table[k];
      out[i * 3 + 1] = table[k + 1];
      out[i * 3 + 2] = table[k + 2];
    }
  }
}

// Fill out (N * 3 bytes) with the colour of every primitive in mode: "camera" (the fitted colour), "semantic" (its
// class's palette colour) or "instance" (its instance's colour). Void and unknown labels take the void colour.
export function paintPoints(mode, scene, out) {
  const { classes, instances } = scene.header;
  const voidColor = scene.header.void.color;
  if (mode === "camera") {
    out.set(scene.color);
  } else if (mode === "semantic") {
    paintLabels(out, scene.semantic, 1, classTable(classes, voidColor), voidColor);
  } else {
    paintLabels(out, scene.instance, 0, instanceTable(instances, voidColor), voidColor);
  }
  return out;
}

// Fill out (N bytes) with each primitive's flag: hidden when its class is hidden; else, while any instance is lit,
// lit or dimmed; else normal. hidden: class indices (-1 is void); lit: a Set of instance ids.
export function flagPoints(semantic, instance, classCount, hidden, lit, out) {
  const hiddenClass = new Uint8Array(classCount + 1);
  for (const c of hidden) if (c >= -1 && c < classCount) hiddenClass[c + 1] = 1;
  const anyLit = lit.size > 0;
  for (let i = 0; i < semantic.length; i++) {
    if (hiddenClass[semantic[i] + 1]) out[i] = FLAG.HIDDEN;
    else if (!anyLit) out[i] = FLAG.NORMAL;
    else out[i] = lit.has(instance[i]) ? FLAG.LIT : FLAG.DIM;
  }
  return out;
}
