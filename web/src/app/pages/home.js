// The home page: the upload card, the job table and the scene list, polled while the page is shown (every second
// while a job is live, else every five).
import { h } from "../../dom.js";
import { api } from "../api-client.js";
import { showError } from "../messages.js";
import { POLL_RETRY_MS, pollDelay, sceneText } from "../rules.js";
import { JOB_COLUMNS, jobRow, updateJobRow } from "./jobs.js";
import { signInPage } from "./sign-in.js";
import { uploadCard } from "./upload.js";

function sceneItem(scene, listMessage, refresh) {
  const remove = async () => {
    if (!confirm(`Delete scene ${scene.name}, its jobs and their results?`)) return;
    try {
      await api("DELETE", `/v1/scenes/${scene.id}`);
    } catch (err) {
      showError(listMessage, err);
    }
    refresh();
  };
  return h(
    "li",
    { "data-scene-id": scene.id },
    sceneText(scene),
    h("button", { type: "button", "data-action": "delete-scene", onclick: remove }, "Delete"),
  );
}

// ctx: { page, route(), onLeave(fn) } (router.js)
export function homePage(ctx) {
  const jobsBody = h("tbody", {});
  const scenesList = h("ul", {});
  const listMessage = h("div", { class: "pgs-message" });
  let timer = null;
  ctx.onLeave(() => clearTimeout(timer));
  let upload = null; // the upload card, made below with refresh as its onQueued
  const refresh = async () => {
    clearTimeout(timer);
    if (!ctx.page.contains(jobsBody)) return;
    let jobs, scenes;
    try {
      [jobs, scenes] = await Promise.all([api("GET", "/v1/jobs?limit=100"), api("GET", "/v1/scenes?limit=200")]);
    } catch (err) {
      if (err.status === 401) return signInPage(ctx);
      showError(listMessage, err);
      timer = setTimeout(refresh, POLL_RETRY_MS);
      return;
    }
    upload.showJobs(jobs.data);
    const byId = new Map(scenes.data.map((s) => [s.id, s]));
    // Rows are updated in place and moved only when the order changes: moving an element takes its focus away,
    // and a re-run form open in a row must keep what is being typed into it while other jobs run.
    const rows = jobs.data.map((job) => {
      const old = jobsBody.querySelector(`tr[data-job-id="${job.id}"]`);
      if (!old) return jobRow(job, byId, refresh);
      updateJobRow(old, job, byId, refresh);
      return old;
    });
    rows.forEach((row, i) => {
      if (jobsBody.children[i] !== row) jobsBody.insertBefore(row, jobsBody.children[i] || null);
    });
    while (jobsBody.children.length > rows.length) jobsBody.lastElementChild.remove();
    scenesList.replaceChildren(...scenes.data.map((s) => sceneItem(s, listMessage, refresh)));
    timer = setTimeout(refresh, pollDelay(jobs.data));
  };
  upload = uploadCard(refresh);
  ctx.page.replaceChildren(
    upload.card,
    h(
      "section",
      { class: "pgs-card" },
      h("h2", {}, "Jobs"),
      listMessage,
      h(
        "table",
        { class: "pgs-jobs", id: "jobs" },
        h("thead", {}, h("tr", {}, ...JOB_COLUMNS.map((t) => h("th", {}, t)))),
        jobsBody,
      ),
    ),
    h("section", { class: "pgs-card" }, h("h2", {}, "Scenes"), scenesList),
  );
  refresh();
}
