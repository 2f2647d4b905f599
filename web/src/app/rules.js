// The app's rules and read-outs that need no DOM: which job states are final, how often to poll, what a row says,
// and the vocabulary field of the re-run form.

export const TERMINAL = new Set(["succeeded", "failed", "canceled"]);
export const POLL_LIVE_MS = 1000; // a job is queued or running
export const POLL_IDLE_MS = 5000;
export const POLL_RETRY_MS = 3000; // the last refresh failed

export function isTerminal(state) {
  return TERMINAL.has(state);
}

export function pollDelay(jobs) {
  return jobs.some((job) => !isTerminal(job.state)) ? POLL_LIVE_MS : POLL_IDLE_MS;
}

export function shortId(id) {
  return id.slice(0, 8);
}

export function jobStateText(job) {
  return job.state + (job.cancel_requested && !isTerminal(job.state) ? " (cancelling)" : "");
}

export function jobProgressText(job) {
  return isTerminal(job.state) ? "" : `${Math.round(job.progress * 100)}%`;
}

// A tiled job's tiles and merge as its row lists them (docs/service.md, "Tiled jobs"): a label, the state, and the
// progress while the tile runs; none for a job that ran whole (or a server from before tiles).
export function tileReadouts(job) {
  return (job.tiles || []).map((tile) => ({
    label: tile.kind === "merge" ? "merge" : `tile ${tile.index + 1}`,
    state: tile.state,
    progress: tile.progress,
    text:
      tile.state === "running"
        ? `${Math.round(tile.progress * 100)}%${tile.stage ? ` ${tile.stage}` : ""}`
        : tile.state + (tile.attempts > 1 ? ` (attempt ${tile.attempts})` : ""),
  }));
}

// The stages a job took from an earlier job's checkpoints of its scene (same inputs and settings, so not computed
// again: docs/service.md, "Stage checkpoints shared by a scene's jobs"), in the order the status lists them.
export function cachedStages(job) {
  return Object.entries(job.stage_cached || {})
    .filter(([, cached]) => cached)
    .map(([stage]) => stage);
}

export function cachedStagesText(job) {
  const stages = cachedStages(job);
  return stages.length ? `reused: ${stages.join(", ")}` : "";
}

// The results (labels, instances, queries, the viewer's point modes) come before the Gaussian fit, which goes on
// after them with its own progress (docs/service.md, "Results before the fit").
export function resultsReady(job) {
  return Boolean(job.results_ready) || job.state === "succeeded";
}

export function fitRunning(job) {
  return job.fit?.state === "running" && !isTerminal(job.state);
}

// gaussians.ply is final (the photo view and renders need it): fitted, or no fit made.
export function sceneFitted(job) {
  return job.fit ? ["succeeded", "skipped"].includes(job.fit.state) : job.state === "succeeded";
}

const FIT_TEXTS = {
  succeeded: "fitted",
  skipped: "not fitted (off)",
  failed: "fit failed",
  canceled: "fit canceled",
};

// What the job table's "Gaussian scene" cell says: nothing before the results, the fit's percentage while it runs.
export function fitText(job) {
  const fit = job.fit;
  if (!fit) return "";
  if (fit.state === "running")
    return isTerminal(job.state) ? "fit stopped" : `fitting ${Math.round(fit.progress * 100)}%`;
  const text = FIT_TEXTS[fit.state] || fit.state;
  return fit.error && fit.state === "failed" ? `${text}: ${fit.error}` : text;
}

// The note above a viewer opened before the fit ended: the fit's progress while it runs, else how it ended.
export function fitNoteText(job) {
  if (fitRunning(job))
    return `The Gaussian scene is being fitted (${Math.round(job.fit.progress * 100)}%); the point views show the results now, the photo view comes when it ends.`;
  return `The Gaussian scene: ${fitText(job) || job.state}; the point views show the results.`;
}

export function sceneText(scene) {
  return `${scene.name} (${(scene.size_bytes / 1e6).toFixed(1)} MB, ${scene.num_frames} frames) `;
}

export function uploadProgressText(sent, total) {
  const mb = (bytes) => (bytes / 1e6).toFixed(1);
  return `uploading ${Math.round((100 * sent) / (total || 1))}% (${mb(sent)} of ${mb(total)} MB)`;
}

// A job's vocabulary is a built-in label set's name or an inline list of classes, never a file of the server
// (docs/service.md). In the form: one name (scannet20, matterport21) or class names separated by commas.
export function vocabularyText(vocabulary) {
  if (!vocabulary) return "";
  return typeof vocabulary === "string" ? vocabulary : vocabulary.classes.map((c) => c.name).join(", ");
}

export function vocabularyBody(text, previous) {
  const value = text.trim();
  if (!value) return undefined;
  if (!value.includes(",")) return value;
  // Classes the job had keep their kind; new ones get the server's default (stuff for wall, floor, ceiling).
  const kinds = new Map(
    (previous && typeof previous === "object" ? previous.classes : []).map((c) => [c.name, c.kind]),
  );
  const names = value
    .split(",")
    .map((n) => n.trim())
    .filter(Boolean);
  return { classes: names.map((name) => (kinds.has(name) ? { name, kind: kinds.get(name) } : { name })) };
}

// The `maps` of the job the upload form starts (docs/service.md, "2D maps: the operator's models"): for each kind of
// map the new scene's bundle lacks, the model chosen in the form; nothing for a kind it brings (naming a model for
// it is refused). chosen: { masks, features }, entry names or "" (none offered).
export function jobMaps(scene, chosen) {
  const maps = {};
  if (scene.has_mask_maps === false && chosen.masks) maps.masks = chosen.masks;
  if (scene.has_feature_maps === false && chosen.features) maps.features = chosen.features;
  return Object.keys(maps).length ? maps : undefined;
}

// What the upload form says while the job starts: the models that will compute the scene's maps, if any.
export function startingJobText(scene, maps) {
  const models = maps ? Object.values(maps).join(" and ") : "";
  return `scene ${scene.name} is valid; starting a job${models ? ` (its 2D maps computed by ${models})` : ""} ...`;
}

// Whether the job the upload form queued has left the queue in the job list (running, or already final): the form's
// "job queued" note then gives way to the job's row. A job not in the list (yet) has not.
export function leftTheQueue(jobs, jobId) {
  const job = jobs.find((j) => j.id === jobId);
  return job !== undefined && job.state !== "queued";
}
