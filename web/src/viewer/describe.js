// What the viewer's panels say about a scene, in which order, and the scene's typical primitive size (the pick
// radius). Pure: strings and arrays in, strings and arrays out.

const mb = (bytes) => (bytes / 1e6).toFixed(1);

export function progressText(received, total) {
  return total
    ? `Loading scene ${Math.round((100 * received) / total)}% (${mb(received)} of ${mb(total)} MB)`
    : `Loading scene (${mb(received)} MB)`;
}

export function summaryText(header) {
  const title = header.title ? `${header.title}: ` : "";
  const decimated = header.total > header.count ? ` (of ${header.total.toLocaleString()}, decimated)` : "";
  return `${title}${header.count.toLocaleString()} primitives${decimated}, ${header.instances.length} instances`;
}

export function hitsText(count, text) {
  return `${count} hit${count === 1 ? "" : "s"} for "${text}"`;
}

// What the query status says of an answer ({hits, candidates, min_score}): the hits, and when none passed, that the
// closest are listed below the threshold (and how to see more of them).
export function answerText(text, answer) {
  const count = answer.hits.length;
  const threshold = formatScore(answer.min_score ?? 0.5);
  if (count || !(answer.candidates || []).length) return `${hitsText(count, text)} (score ≥ ${threshold})`;
  return `no instance scored ≥ ${threshold} for "${text}"; the closest, below it (lower the threshold to light them):`;
}

// Scores as the hit list shows them: two decimals, the threshold likewise.
export function formatScore(score) {
  return Number(score).toFixed(2);
}

// A hit's or candidate's score in the answer list: three decimals, or, under what three decimals show (0.000), two
// significant digits (3.0e-5), so that the order of answers that all score near 0 still shows.
export function hitScoreText(score) {
  const value = Number(score);
  return value !== 0 && Math.abs(value) < 0.0005 ? value.toExponential(1) : value.toFixed(3);
}

// The legend: classes that have primitives, in vocabulary order, then void when some primitives are void.
export function legendRows(header) {
  const rows = header.classes
    .filter((c) => c.count > 0)
    .map((c) => ({ index: c.index, name: c.name, kind: c.kind, color: c.color, count: c.count }));
  if (header.void.count > 0)
    rows.push({ index: -1, name: "(void)", kind: "", color: header.void.color, count: header.void.count });
  return rows;
}

// The instance list: by class name, then id.
export function instanceOrder(instances) {
  return [...instances].sort((a, b) => a.class_name.localeCompare(b.class_name) || a.id - b.id);
}

export function instanceTitle(inst) {
  const size = inst.bbox_max.map((v, i) => (v - inst.bbox_min[i]).toFixed(2)).join("×");
  return `${inst.num_points} primitives, box ${size} m`;
}

// The median of about 1000 evenly spaced radii (0.01 m for an empty scene).
export function medianScale(scale) {
  const sample = [];
  const step = Math.max(1, Math.floor(scale.length / 1000));
  for (let i = 0; i < scale.length; i += step) sample.push(scale[i]);
  sample.sort((a, b) => a - b);
  return sample.length ? sample[sample.length >> 1] : 0.01;
}
