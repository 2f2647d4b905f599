// The job table's rows: state, stage (and the stages reused from an earlier job's checkpoints), progress (of a tiled
// job, per tile too), the Gaussian fit (after the results), error, and the actions (open the viewer once the results
// are ready, cancel, re-run with other settings, delete). A row's data-state, data-results, data-fit and
// data-cached are what the browser tests wait on; each tile's line carries data-tile and data-tile-state.
import { h } from "../../dom.js";
import { api } from "../api-client.js";
import { showError } from "../messages.js";
import {
  cachedStages,
  cachedStagesText,
  fitRunning,
  fitText,
  isTerminal,
  jobProgressText,
  jobStateText,
  resultsReady,
  shortId,
  tileReadouts,
} from "../rules.js";
import { rerunForm } from "./rerun.js";

export const JOB_COLUMNS = ["job", "scene", "state", "stage", "progress", "Gaussian scene", "", ""];

function fitCell(job) {
  const cell = h("td", { class: "pgs-fit" });
  if (fitRunning(job)) cell.append(h("progress", { max: 1, value: job.fit.progress }), " ");
  cell.append(fitText(job));
  return cell;
}

function progressCell(job) {
  const cell = h("td", {});
  if (!isTerminal(job.state)) cell.append(h("progress", { max: 1, value: job.progress }), " ");
  cell.append(jobProgressText(job));
  const tiles = tileReadouts(job);
  if (tiles.length)
    cell.append(
      h(
        "ul",
        { class: "pgs-tiles" },
        ...tiles.map((tile) =>
          h(
            "li",
            { "data-tile": tile.label, "data-tile-state": tile.state },
            `${tile.label}: `,
            tile.state === "running" ? h("progress", { max: 1, value: tile.progress }) : "",
            ` ${tile.text}`,
          ),
        ),
      ),
    );
  return cell;
}

// One row per job, made once and then updated in place as the job moves on (updateJobRow): its message box, and a
// re-run form open in it, stay the same elements, so what is typed there and its focus outlive the table's polls.
// scenes: Map id -> scene; refresh(): reload the table after an action
export function jobRow(job, scenes, refresh) {
  const message = h("div", { class: "pgs-message", "data-role": "message" });
  const row = h("tr", { "data-job-id": job.id });
  row.append(...jobCells(job, scenes, refresh, message));
  row.children[MESSAGE_CELL].append(message);
  setRowState(row, job);
  return row;
}

// Bring a row made by jobRow to the job's latest status; nothing is done when the job shows as it did.
export function updateJobRow(row, job, scenes, refresh) {
  const shown = JSON.stringify(job);
  if (row.pgsShown === shown) return;
  const message = row.querySelector("[data-role=message]");
  jobCells(job, scenes, refresh, message).forEach((cell, i) => {
    const old = row.children[i];
    if (i !== MESSAGE_CELL) return old.replaceWith(cell);
    old.querySelector("[data-role=error]").replaceWith(cell.querySelector("[data-role=error]"));
  });
  setRowState(row, job, shown);
}

function setRowState(row, job, shown = JSON.stringify(job)) {
  row.pgsShown = shown;
  Object.assign(row.dataset, {
    state: job.state,
    results: resultsReady(job) ? "ready" : "pending",
    fit: job.fit?.state || "",
    cached: cachedStages(job).join(" "),
  });
}

const MESSAGE_CELL = 6; // the error and message box; the message box itself is the row's own (jobRow)

// The row's cells, the message cell holding only the error: the actions show their errors in `message`.
function jobCells(job, scenes, refresh, message) {
  const sceneName = scenes.get(job.scene_id)?.name || shortId(job.scene_id);
  const act = (label, fn) =>
    h(
      "button",
      {
        type: "button",
        "data-action": label.toLowerCase(),
        onclick: async () => {
          try {
            await fn();
            refresh();
          } catch (err) {
            showError(message, err);
          }
        },
      },
      label,
    );
  const actions = h("td", {});
  if (resultsReady(job))
    actions.append(h("a", { href: `#/jobs/${job.id}`, "data-action": "open" }, "Open viewer"), " ");
  if (!isTerminal(job.state))
    actions.append(
      act("Cancel", () => api("POST", `/v1/jobs/${job.id}/cancel`)),
      " ",
    );
  actions.append(
    act("Re-run", async () => rerunForm(job, message, refresh)),
    " ",
  );
  actions.append(
    act("Delete", async () => {
      if (!confirm(`Delete job ${shortId(job.id)} and its results?`)) return;
      await api("DELETE", `/v1/jobs/${job.id}`);
    }),
  );
  const error = job.error
    ? h("span", { class: "pgs-message pgs-bad", "data-role": "error" }, `${job.error.type}: ${job.error.message}`)
    : h("span", { "data-role": "error" });
  return [
    h("td", {}, h("code", {}, shortId(job.id))),
    h("td", {}, sceneName),
    h("td", { class: `pgs-state-${job.state}` }, jobStateText(job)),
    h("td", {}, job.stage || "", cachedStagesText(job) ? h("div", { class: "pgs-cached" }, cachedStagesText(job)) : ""),
    progressCell(job),
    fitCell(job),
    h("td", {}, error),
    actions,
  ];
}
