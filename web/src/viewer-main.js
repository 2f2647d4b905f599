// The viewer on its own page: `panogs view RUN_DIR` (scene, queries and gaussians.ply from the local server) or the
// offline file of `panogs export-html` (the scene inline as base64; class-name queries answered from the answers
// the file carries, computed by the same query code as the API). The view state lives in the URL's fragment.
// Two entry points call startViewer: view-main.js (`panogs view`, an ES module that can load the photo view's
// chunk) and viewer-standalone.js (one classic script that the offline file inlines, without Spark's 3 MB).
import { base64ToBuffer, fetchScene, parseScene } from "./scene.js";
import { paramsToState, stateToParams } from "./viewer/url-state.js";
import { Viewer } from "./viewer/viewer.js";

async function localQuery(url, text, options) {
  const response = await fetch(url, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ text, ...options }),
  });
  const body = await response.json();
  if (!response.ok) throw new Error([body.message, ...(body.problems || [])].join("\n"));
  return body;
}

async function fetchJson(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: ${response.status}`);
  return response.json();
}

function offlineQuery(header, text) {
  const answer = (header.class_queries || {})[text.trim().toLowerCase()];
  if (!answer) {
    const names = Object.keys(header.class_queries || {}).join(", ");
    return Promise.reject(
      new Error(`this offline file answers class names only (${names}); free text needs \`panogs view\``),
    );
  }
  return Promise.resolve(answer);
}

// photo: the Viewer's photo option (load and bytes of the Gaussian scene), or null where there is none.
export async function startViewer(photo) {
  const root = document.getElementById("viewer");
  const inline = document.getElementById("panogs-scene");
  const params = new URLSearchParams(location.hash.slice(1));
  let header = null;
  const viewer = new Viewer(root, {
    state: paramsToState(params),
    photo: inline ? null : photo,
    canAsk: !inline, // the offline file's answers were computed at the default threshold
    cameras: inline ? async () => header.cameras || { frames: [] } : () => fetchJson("cameras.json"),
    queryFn: (text, options) => (inline ? offlineQuery(header, text) : localQuery("query", text, options)),
    onStateChange: (state) => history.replaceState(null, "", "#" + stateToParams(state).toString()),
  });
  window.__panogs = { viewer, startedAt: performance.now() };
  try {
    const scene = inline
      ? parseScene(base64ToBuffer(inline.textContent.trim()))
      : await fetchScene("scene.bin", (got, total) => viewer.showProgress(got, total));
    header = scene.header;
    if (header.title) document.title = `${header.title} · panogs viewer`;
    viewer.load(scene);
    window.__panogs.readyAt = performance.now();
  } catch (err) {
    viewer.showError(`Could not open the scene: ${err.message}`);
  }
}
