// The upload card: a bundle sent over tus (tus-js-client; a dropped connection resumes from the server's offset),
// then validated into a scene and queued as a job. A bundle without its own 2D maps (posed colour and depth alone) has
// them computed by the operator's models, chosen here from those the server lists (GET /v1/map-models).
import * as tus from "tus-js-client";
import { h } from "../../dom.js";
import { APP_HEADER, api, tusError } from "../api-client.js";
import { showError } from "../messages.js";
import { jobMaps, leftTheQueue, startingJobText, uploadProgressText } from "../rules.js";

const CHUNK_BYTES = 8 * 1024 * 1024;
// How long "job queued" stays under the form at most: the job's row in the table below says the rest of its life,
// and the note goes sooner when the row shows the job running or done (a small job can finish within this time).
const QUEUED_NOTE_MS = 6000;
const RETRY_DELAYS_MS = [0, 1000, 3000, 5000, 10000];

// onQueued(): a job was queued (the job list refreshes). Returns the card, and showJobs(jobs): the job list as the
// page last read it, so that the "job queued" note goes once the queued job's row shows more.
export function uploadCard(onQueued) {
  let queuedNote = null; // { text, jobId } while the form says "job queued"
  const file = h("input", {
    type: "file",
    name: "bundle",
    accept: ".zip,.tar.gz,.tgz,.tar",
    "aria-label": "scene bundle",
  });
  const name = h("input", {
    type: "text",
    name: "name",
    placeholder: "scene name (optional)",
    "aria-label": "scene name",
  });
  const bar = h("progress", { max: 1, value: 0, hidden: true });
  const message = h("div", { class: "pgs-message", id: "upload-message", "aria-live": "polite" });
  const start = h("button", { type: "submit" }, "Upload and run");
  const masksModel = h("select", { name: "masks-model", "aria-label": "masks model" });
  const featuresModel = h("select", { name: "features-model", "aria-label": "features model" });
  const models = h(
    "fieldset",
    { class: "pgs-map-models", hidden: true },
    h("legend", {}, "2D models, for a bundle without its own masks or feature maps"),
    h("label", { class: "pgs-field" }, h("span", {}, "masks"), masksModel),
    h("label", { class: "pgs-field" }, h("span", {}, "features (and free text)"), featuresModel),
  );
  // The operator's entries; none (or a server without the route) leaves the choice hidden and the job without maps.
  api("GET", "/v1/map-models").then(
    (listed) => {
      masksModel.replaceChildren(...listed.masks.map((name) => h("option", { value: name }, name)));
      featuresModel.replaceChildren(...listed.features.map((name) => h("option", { value: name }, name)));
      models.hidden = !listed.masks.length && !listed.features.length;
    },
    () => {},
  );

  // The note goes if it is still the one shown (an error or a new upload may have replaced it).
  const clearQueuedNote = (text) => {
    if (message.textContent === text) message.textContent = "";
    if (queuedNote && queuedNote.text === text) queuedNote = null;
  };
  const showJobs = (jobs) => {
    if (queuedNote && leftTheQueue(jobs, queuedNote.jobId)) clearQueuedNote(queuedNote.text);
  };

  const createJob = async (uploadId) => {
    message.textContent = "validating the bundle ...";
    try {
      const scene = await api("POST", "/v1/scenes", { upload_id: uploadId, name: name.value.trim() || undefined });
      const maps = jobMaps(scene, { masks: masksModel.value, features: featuresModel.value });
      message.textContent = startingJobText(scene, maps);
      const job = await api("POST", "/v1/jobs", { scene_id: scene.id, maps });
      const queued = `scene ${scene.name}: job queued (its row is in the jobs below)`;
      message.textContent = queued;
      queuedNote = { text: queued, jobId: job.id };
      setTimeout(() => clearQueuedNote(queued), QUEUED_NOTE_MS);
      form.reset(); // the selects go back to their first entry
      bar.hidden = true;
      onQueued();
    } catch (err) {
      showError(message, err);
    } finally {
      start.disabled = false;
    }
  };

  const send = (chosen) => {
    const upload = new tus.Upload(chosen, {
      endpoint: "/v1/uploads",
      headers: APP_HEADER,
      metadata: { filename: chosen.name },
      chunkSize: CHUNK_BYTES,
      retryDelays: RETRY_DELAYS_MS,
      removeFingerprintOnSuccess: true,
      onProgress: (sent, total) => {
        bar.value = total ? sent / total : 0;
        message.textContent = uploadProgressText(sent, total);
      },
      onError: (err) => {
        start.disabled = false;
        showError(message, tusError(err));
      },
      onSuccess: () => createJob(upload.url.split("/").pop()),
    });
    upload.findPreviousUploads().then((previous) => {
      if (previous.length) upload.resumeFromPreviousUpload(previous[0]);
      upload.start();
    });
  };

  const form = h(
    "form",
    {
      class: "pgs-card",
      id: "upload",
      onsubmit: (e) => {
        e.preventDefault();
        const chosen = file.files[0];
        if (!chosen) return showError(message, new Error("choose a bundle: a .zip or .tar.gz of a scene folder"));
        start.disabled = true;
        bar.hidden = false;
        message.className = "pgs-message";
        message.textContent = "uploading ...";
        send(chosen);
      },
    },
    h("h2", {}, "Upload a scene bundle"),
    file,
    " ",
    name,
    " ",
    start,
    " ",
    bar,
    models,
    message,
  );
  return { card: form, showJobs };
}
