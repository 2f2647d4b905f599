// The viewer on a job whose results are ready (the Gaussian fit may still run: the point modes need only the
// results): the job checked first (another tenant's job, a deleted one or one without results shows why it cannot
// open, with the way back to the jobs), then the scene streamed with progress. While the fit runs the job is asked
// again, as the job table does, and the photo view is offered the moment the fit ends: no reload. The view state is
// kept in the route's parameters; the page's title is the scene's name.
import { h } from "../../dom.js";
import { fetchScene } from "../../scene.js";
import { paramsToState, stateToParams } from "../../viewer/url-state.js";
import { Viewer } from "../../viewer/viewer.js";
import { APP_HEADER, api } from "../api-client.js";
import { showError } from "../messages.js";
import { viewerHash } from "../routes.js";
import { POLL_LIVE_MS, POLL_RETRY_MS, fitNoteText, fitRunning, resultsReady, sceneFitted } from "../rules.js";

const backLink = () => h("a", { href: "#/", class: "pgs-back", "data-action": "back" }, "← back to the jobs");

// A message box with an error and the way back (a deleted job's URL is no dead end).
function showDeadEnd(message, err) {
  showError(message, err);
  message.append(" ", backLink());
}

// The photo view's source: the job's gaussians.ply, final once the fit is done (it answers 409 before).
function photoSource(jobId) {
  return {
    load: () => import("../../viewer/photo.js"),
    bytes: async () => {
      const response = await fetch(`/v1/jobs/${jobId}/artifacts/gaussians.ply`, { headers: APP_HEADER });
      if (!response.ok) throw new Error(`gaussians.ply: ${response.status}`);
      return new Uint8Array(await response.arrayBuffer());
    },
  };
}

// Asks for the job while its fit runs; onFitted() once the scene is final, the note follows the fit. Returns stop().
function watchFit(jobId, note, onFitted) {
  let timer = null;
  let stopped = false;
  const poll = async () => {
    let job;
    try {
      job = await api("GET", `/v1/jobs/${jobId}`);
    } catch (_) {
      if (!stopped) timer = setTimeout(poll, POLL_RETRY_MS);
      return;
    }
    if (stopped) return;
    if (sceneFitted(job)) {
      note.remove();
      return onFitted();
    }
    note.textContent = fitNoteText(job);
    if (fitRunning(job)) timer = setTimeout(poll, POLL_LIVE_MS);
  };
  timer = setTimeout(poll, POLL_LIVE_MS);
  return () => {
    stopped = true;
    clearTimeout(timer);
  };
}

// The scene's name, shown as the page's title (null when it cannot be read: the title stays the app's).
async function showSceneName(job) {
  try {
    const scene = await api("GET", `/v1/scenes/${job.scene_id}`);
    document.title = `${scene.name} · panogs viewer`;
    return scene.name;
  } catch (_) {
    return null;
  }
}

// ctx: { page, onLeave(fn) } (router.js)
export async function viewerPage(ctx, jobId, params) {
  const root = h("div", { id: "viewer" });
  const message = h("div", { class: "pgs-message" });
  ctx.page.replaceChildren(message, root);
  let job;
  try {
    job = await api("GET", `/v1/jobs/${jobId}`);
  } catch (err) {
    root.remove();
    return showDeadEnd(message, err);
  }
  if (!resultsReady(job)) {
    root.remove();
    return showDeadEnd(message, new Error(`job ${jobId} is ${job.state}; the viewer opens once its results are ready`));
  }
  const title = document.title;
  ctx.onLeave(() => (document.title = title));
  const sceneName = showSceneName(job);
  root.style.height = "100%"; // through the CSSOM: the page's CSP refuses style attributes
  const fitted = sceneFitted(job);
  const viewer = new Viewer(root, {
    state: paramsToState(params),
    photo: fitted ? photoSource(jobId) : null,
    queryFn: (text, options) => api("POST", `/v1/jobs/${jobId}/query`, { text, ...options }),
    cameras: () => api("GET", `/v1/jobs/${jobId}/artifacts/cameras.json`),
    onStateChange: (state) => history.replaceState(null, "", viewerHash(jobId, stateToParams(state))),
  });
  ctx.onLeave(() => viewer.dispose());
  if (fitRunning(job)) {
    message.className = "pgs-message pgs-fit-note";
    message.textContent = fitNoteText(job);
    ctx.onLeave(watchFit(jobId, message, () => viewer.offerPhoto(photoSource(jobId))));
  } else message.remove();
  window.__panogs = { viewer, startedAt: performance.now() };
  try {
    const scene = await fetchScene(`/v1/jobs/${jobId}/viewer-scene`, (got, total) => viewer.showProgress(got, total), {
      headers: APP_HEADER,
    });
    // The summary names the scene, not the job's id (which the job table shows).
    scene.header.title = (await sceneName) || scene.header.title;
    viewer.load(scene);
    window.__panogs.readyAt = performance.now();
  } catch (err) {
    viewer.showError(`Could not open the scene: ${err.message}`);
    ctx.page.prepend(h("div", { class: "pgs-message" }, backLink()));
  }
}
