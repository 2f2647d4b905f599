// The app's routes, kept in the URL's fragment: #/ (uploads, jobs, scenes) and #/jobs/<id>?<view state> (the
// viewer on a finished job). No DOM.

const VIEWER_PATH = /^\/jobs\/([0-9a-f-]{36})$/;

// The part before "?": the viewer rewrites what follows as the view changes, which is no new page.
export function routePath(hash) {
  return hash.split("?")[0];
}

// { page: "viewer", jobId, params } or { page: "home" }
export function parseRoute(hash) {
  const [path, query] = hash.replace(/^#/, "").split("?");
  const match = VIEWER_PATH.exec(path || "");
  if (match) return { page: "viewer", jobId: match[1], params: new URLSearchParams(query || "") };
  return { page: "home" };
}

export function viewerHash(jobId, params) {
  return `#/jobs/${jobId}?${params}`;
}
