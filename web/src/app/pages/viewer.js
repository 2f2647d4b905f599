// The viewer on a job whose results are ready (the Gaussian fit may still run: the point modes need only the
// results): the job checked first (another tenant's job or one without results shows why it cannot open), then the
// scene streamed with progress. The view state is kept in the route's parameters.
import { h } from "../../dom.js";
import { fetchScene } from "../../scene.js";
import { paramsToState, stateToParams } from "../../viewer/url-state.js";
import { Viewer } from "../../viewer/viewer.js";
import { APP_HEADER, api } from "../api-client.js";
import { showError } from "../messages.js";
import { viewerHash } from "../routes.js";
import { fitRunning, resultsReady, sceneFitted } from "../rules.js";

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
    return showError(message, err);
  }
  if (!resultsReady(job)) {
    root.remove();
    return showError(message, new Error(`job ${jobId} is ${job.state}; the viewer opens once its results are ready`));
  }
  if (fitRunning(job)) {
    message.className = "pgs-message pgs-fit-note";
    message.textContent = `The Gaussian scene is being fitted (${Math.round(job.fit.progress * 100)}%); the point views show the results now.`;
  } else message.remove();
  root.style.height = "100%"; // through the CSSOM: the page's CSP refuses style attributes
  // The photo view needs the fitted scene: offered once the fit is done (gaussians.ply answers 409 before).
  const photo = sceneFitted(job)
    ? {
        load: () => import("../../viewer/photo.js"),
        bytes: async () => {
          const response = await fetch(`/v1/jobs/${jobId}/artifacts/gaussians.ply`, { headers: APP_HEADER });
          if (!response.ok) throw new Error(`gaussians.ply: ${response.status}`);
          return new Uint8Array(await response.arrayBuffer());
        },
      }
    : null;
  const viewer = new Viewer(root, {
    state: paramsToState(params),
    photo,
    queryFn: (text) => api("POST", `/v1/jobs/${jobId}/query`, { text }),
    onStateChange: (state) => history.replaceState(null, "", viewerHash(jobId, stateToParams(state))),
  });
  ctx.onLeave(() => viewer.dispose());
  window.__panogs = { viewer, startedAt: performance.now() };
  try {
    const scene = await fetchScene(`/v1/jobs/${jobId}/viewer-scene`, (got, total) => viewer.showProgress(got, total), {
      headers: APP_HEADER,
    });
    viewer.load(scene);
    window.__panogs.readyAt = performance.now();
  } catch (err) {
    viewer.showError(`Could not open the scene: ${err.message}`);
  }
}
