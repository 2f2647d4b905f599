// The app: sign in (the API key is exchanged once for a short-lived HttpOnly session cookie and never kept),
// upload a bundle over tus with tus-js-client, watch jobs live, cancel, re-run, delete, open the viewer.
// Routes live in the hash: #/ (uploads, jobs, scenes) and #/jobs/<id>?mode=...&sel=...&q=...&cam=... (the viewer).
import * as tus from "tus-js-client";
import { paramsToState, stateToParams } from "./viewer/url-state.js";
import { Viewer } from "./viewer/viewer.js";
import { fetchScene } from "./scene.js";

const page = document.getElementById("page");
const who = document.getElementById("who");
const signOut = document.getElementById("sign-out");
// Sent with every call: a cross-site form cannot set it, so a cookie-authenticated write must come from this app.
const APP_HEADER = { "X-Panogs-App": "1" };
const TERMINAL = new Set(["succeeded", "failed", "canceled"]);
let pollTimer = null;
let viewer = null;

class ApiError extends Error {
  constructor(status, body) {
    super(body.message || `HTTP ${status}`);
    this.status = status;
    this.problems = body.problems || [];
  }
}

async function api(method, path, body) {
  const init = { method, credentials: "same-origin", headers: { ...APP_HEADER } };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(path, init);
  if (response.status === 204) return null;
  const text = await response.text();
  let parsed = {};
  try {
    parsed = text ? JSON.parse(text) : {};
  } catch (_) {
    parsed = { message: text };
  }
  if (!response.ok) throw new ApiError(response.status, parsed);
  return parsed;
}

function h(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (key === "class") node.className = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (value !== undefined && value !== null && value !== false) node.setAttribute(key, value === true ? "" : value);
  }
  for (const child of children) if (child !== null && child !== undefined) node.append(child);
  return node;
}

function showError(box, err) {
  box.className = "pgs-message pgs-bad";
  box.replaceChildren(err.message);
  if (err.problems && err.problems.length) {
    box.append(h("ul", { class: "pgs-problems" }, ...err.problems.map((p) => h("li", {}, p))));
  }
}

// --- sign in ---------------------------------------------------------------------------------------------------

async function currentSession() {
  try {
    return await api("GET", "/app/session");
  } catch (err) {
    if (err.status === 401) return null;
    throw err;
  }
}

function signInPage() {
  const key = h("input", { type: "password", name: "key", autocomplete: "off", placeholder: "pgs_...", "aria-label": "API key", size: 60 });
  const message = h("div", { class: "pgs-message" });
  const form = h(
    "form",
    {
      class: "pgs-card",
      id: "sign-in",
      onsubmit: async (e) => {
        e.preventDefault();
        const value = key.value.trim();
        key.value = ""; // the key is not kept anywhere once sent
        try {
          await api("POST", "/app/session", { key: value });
          route();
        } catch (err) {
          showError(message, err);
        }
      },
    },
    h("h2", {}, "Sign in"),
    h("p", { class: "pgs-message" }, "Paste an API key (panogs keys create --name you). It is exchanged for a session cookie and not stored."),
    key,
    " ",
    h("button", { type: "submit" }, "Sign in"),
    message,
  );
  page.replaceChildren(form);
  key.focus();
}

signOut.addEventListener("click", async () => {
  await api("DELETE", "/app/session").catch(() => null);
  location.hash = "#/";
  route();
});

// --- home: upload, jobs, scenes --------------------------------------------------------------------------------

function uploadCard(onScene) {
  const file = h("input", { type: "file", name: "bundle", accept: ".zip,.tar.gz,.tgz,.tar", "aria-label": "scene bundle" });
  const name = h("input", { type: "text", name: "name", placeholder: "scene name (optional)", "aria-label": "scene name" });
  const bar = h("progress", { max: 1, value: 0, hidden: true });
  const message = h("div", { class: "pgs-message", id: "upload-message", "aria-live": "polite" });
  let upload = null;
  const start = h("button", { type: "submit" }, "Upload and run");
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
        upload = new tus.Upload(chosen, {
          endpoint: "/v1/uploads",
          headers: APP_HEADER,
          metadata: { filename: chosen.name },
          chunkSize: 8 * 1024 * 1024,
          retryDelays: [0, 1000, 3000, 5000, 10000], // a dropped connection resumes from the server's offset
          removeFingerprintOnSuccess: true,
          onProgress: (sent, total) => {
            bar.value = total ? sent / total : 0;
            message.textContent = `uploading ${Math.round((100 * sent) / (total || 1))}% (${(sent / 1e6).toFixed(1)} of ${(total / 1e6).toFixed(1)} MB)`;
          },
          onError: (err) => {
            start.disabled = false;
            let body = {};
            try {
              body = JSON.parse(err.originalResponse?.getBody() || "{}");
            } catch (_) {
              /* not JSON */
            }
            showError(message, new ApiError(err.originalResponse?.getStatus() || 0, { message: body.message || String(err.message || err), problems: body.problems }));
          },
          onSuccess: async () => {
            const uploadId = upload.url.split("/").pop();
            message.textContent = "validating the bundle ...";
            try {
              const scene = await api("POST", "/v1/scenes", { upload_id: uploadId, name: name.value.trim() || undefined });
              message.textContent = `scene ${scene.name} is valid; starting a job ...`;
              await api("POST", "/v1/jobs", { scene_id: scene.id });
              message.textContent = `scene ${scene.name}: job queued`;
              form.reset();
              bar.hidden = true;
              onScene();
            } catch (err) {
              showError(message, err);
            } finally {
              start.disabled = false;
            }
          },
        });
        upload.findPreviousUploads().then((previous) => {
          if (previous.length) upload.resumeFromPreviousUpload(previous[0]);
          upload.start();
        });
      },
    },
    h("h2", {}, "Upload a scene bundle"),
    file, " ", name, " ", start, " ", bar,
    message,
  );
  return form;
}

function jobRow(job, scenes, refresh) {
  const sceneName = scenes.get(job.scene_id)?.name || job.scene_id.slice(0, 8);
  const message = h("div", { class: "pgs-message" });
  const act = (label, fn, attrs = {}) =>
    h("button", { type: "button", "data-action": label.toLowerCase(), ...attrs, onclick: async () => {
      try {
        await fn();
        refresh();
      } catch (err) {
        showError(message, err);
      }
    } }, label);
  const actions = h("td", {});
  if (job.state === "succeeded") actions.append(h("a", { href: `#/jobs/${job.id}`, "data-action": "open" }, "Open viewer"), " ");
  if (!TERMINAL.has(job.state)) actions.append(act("Cancel", () => api("POST", `/v1/jobs/${job.id}/cancel`)), " ");
  actions.append(act("Re-run", async () => rerunForm(job, message, refresh)), " ");
  actions.append(
    act("Delete", async () => {
      if (!confirm(`Delete job ${job.id.slice(0, 8)} and its results?`)) return;
      await api("DELETE", `/v1/jobs/${job.id}`);
    }),
  );
  const progress = TERMINAL.has(job.state) ? "" : `${Math.round(job.progress * 100)}%`;
  return h(
    "tr",
    { "data-job-id": job.id, "data-state": job.state },
    h("td", {}, h("code", {}, job.id.slice(0, 8))),
    h("td", {}, sceneName),
    h("td", { class: `pgs-state-${job.state}` }, job.state + (job.cancel_requested && !TERMINAL.has(job.state) ? " (cancelling)" : "")),
    h("td", {}, job.stage || ""),
    h("td", {}, TERMINAL.has(job.state) ? "" : h("progress", { max: 1, value: job.progress }), " ", progress),
    h("td", {}, job.error ? h("span", { class: "pgs-message pgs-bad" }, `${job.error.type}: ${job.error.message}`) : "", message),
    actions,
  );
}

// A job's vocabulary is a built-in label set's name or an inline list of classes, never a file of the server
// (docs/service.md). In the form: one name (scannet20, matterport21) or class names separated by commas.
function vocabularyText(vocabulary) {
  if (!vocabulary) return "";
  return typeof vocabulary === "string" ? vocabulary : vocabulary.classes.map((c) => c.name).join(", ");
}

function vocabularyBody(text, previous) {
  const value = text.trim();
  if (!value) return undefined;
  if (!value.includes(",")) return value;
  // Classes the job had keep their kind; new ones get the server's default (stuff for wall, floor, ceiling).
  const kinds = new Map((previous && typeof previous === "object" ? previous.classes : []).map((c) => [c.name, c.kind]));
  const names = value.split(",").map((n) => n.trim()).filter(Boolean);
  return { classes: names.map((name) => (kinds.has(name) ? { name, kind: kinds.get(name) } : { name })) };
}

function rerunForm(job, message, refresh) {
  const config = h("textarea", { rows: 4, cols: 60, "aria-label": "settings (JSON)" });
  config.value = JSON.stringify(job.config || {}, null, 1);
  const vocabulary = h("input", {
    type: "text", size: 40, "aria-label": "vocabulary",
    placeholder: "vocabulary (optional): scannet20 | matterport21 | lamp, rug, ...",
  });
  vocabulary.value = vocabularyText(job.vocabulary);
  const form = h(
    "form",
    {
      onsubmit: async (e) => {
        e.preventDefault();
        let parsed;
        try {
          parsed = JSON.parse(config.value || "{}");
        } catch (err) {
          return showError(message, new Error(`settings: not valid JSON (${err.message})`));
        }
        try {
          await api("POST", "/v1/jobs", { scene_id: job.scene_id, config: parsed, vocabulary: vocabularyBody(vocabulary.value, job.vocabulary) });
          refresh();
        } catch (err) {
          showError(message, err);
        }
      },
    },
    h("div", {}, "Settings (PipelineConfig overrides, e.g. {\"clustering\": {\"thresholds\": [0.9, 0.7]}}):"),
    config, h("br"), vocabulary, " ", h("button", { type: "submit" }, "Run"),
  );
  message.className = "pgs-message";
  message.replaceChildren(form);
}

async function homePage() {
  const jobsBody = h("tbody", {});
  const scenesList = h("ul", {});
  const listMessage = h("div", { class: "pgs-message" });
  const refresh = async () => {
    clearTimeout(pollTimer);
    if (!page.contains(jobsBody)) return;
    let jobs, scenes;
    try {
      [jobs, scenes] = await Promise.all([api("GET", "/v1/jobs?limit=100"), api("GET", "/v1/scenes?limit=200")]);
    } catch (err) {
      if (err.status === 401) return signInPage();
      showError(listMessage, err);
      pollTimer = setTimeout(refresh, 3000);
      return;
    }
    const byId = new Map(scenes.data.map((s) => [s.id, s]));
    // Keep an open re-run form: rebuild only the rows whose job changed.
    jobsBody.replaceChildren(...jobs.data.map((job) => {
      const old = jobsBody.querySelector(`[data-job-id="${job.id}"]`);
      if (old && old.dataset.state === job.state && TERMINAL.has(job.state)) return old;
      return jobRow(job, byId, refresh);
    }));
    scenesList.replaceChildren(...scenes.data.map((s) => h("li", { "data-scene-id": s.id }, `${s.name} (${(s.size_bytes / 1e6).toFixed(1)} MB, ${s.num_frames} frames) `,
      h("button", { type: "button", "data-action": "delete-scene", onclick: async () => {
        if (!confirm(`Delete scene ${s.name}, its jobs and their results?`)) return;
        try {
          await api("DELETE", `/v1/scenes/${s.id}`);
        } catch (err) {
          showError(listMessage, err);
        }
        refresh();
      } }, "Delete"))));
    const live = jobs.data.some((j) => !TERMINAL.has(j.state));
    pollTimer = setTimeout(refresh, live ? 1000 : 5000);
  };
  page.replaceChildren(
    uploadCard(refresh),
    h("section", { class: "pgs-card" }, h("h2", {}, "Jobs"), listMessage,
      h("table", { class: "pgs-jobs", id: "jobs" },
        h("thead", {}, h("tr", {}, ...["job", "scene", "state", "stage", "progress", "", ""].map((t) => h("th", {}, t)))),
        jobsBody)),
    h("section", { class: "pgs-card" }, h("h2", {}, "Scenes"), scenesList),
  );
  refresh();
}

// --- the viewer ----------------------------------------------------------------------------------------------

async function viewerPage(jobId, params) {
  const root = h("div", { id: "viewer" });
  const message = h("div", { class: "pgs-message" });
  page.replaceChildren(message, root);
  let job;
  try {
    job = await api("GET", `/v1/jobs/${jobId}`);
  } catch (err) {
    root.remove();
    return showError(message, err);
  }
  if (job.state !== "succeeded") {
    root.remove();
    return showError(message, new Error(`job ${jobId} is ${job.state}; the viewer opens once it has succeeded`));
  }
  message.remove();
  root.style.height = "100%";
  viewer = new Viewer(root, {
    state: paramsToState(params),
    queryFn: (text) => api("POST", `/v1/jobs/${jobId}/query`, { text }),
    onStateChange: (state) => history.replaceState(null, "", `#/jobs/${jobId}?${stateToParams(state)}`),
  });
  window.__panogs = { viewer, startedAt: performance.now() };
  try {
    const scene = await fetchScene(`/v1/jobs/${jobId}/viewer-scene`, (got, total) => viewer.showProgress(got, total), { headers: APP_HEADER });
    viewer.load(scene);
    window.__panogs.readyAt = performance.now();
  } catch (err) {
    viewer.showError(`Could not open the scene: ${err.message}`);
  }
}

// --- routing -------------------------------------------------------------------------------------------------

async function route() {
  clearTimeout(pollTimer);
  if (viewer) {
    viewer.dispose();
    viewer = null;
  }
  const session = await currentSession().catch(() => null);
  who.textContent = session ? `signed in as ${session.tenant}` : "";
  signOut.hidden = !session;
  if (!session) return signInPage();
  const [path, query] = location.hash.replace(/^#/, "").split("?");
  const match = /^\/jobs\/([0-9a-f-]{36})$/.exec(path || "");
  if (match) return viewerPage(match[1], new URLSearchParams(query || ""));
  return homePage();
}

let lastPath = null;
window.addEventListener("hashchange", () => {
  // The viewer rewrites its own parameters as the view changes; only a new path is a new page.
  const path = location.hash.split("?")[0];
  if (path !== lastPath) {
    lastPath = path;
    route();
  }
});
lastPath = location.hash.split("?")[0];
route();
