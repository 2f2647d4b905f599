// The router: the session decides between the sign-in page and the others, the fragment between the home page and
// the viewer (routes.js). Leaving a page runs what it registered (stop polling, dispose the viewer).
import { api, currentSession } from "./api-client.js";
import { homePage } from "./pages/home.js";
import { signInPage } from "./pages/sign-in.js";
import { viewerPage } from "./pages/viewer.js";
import { parseRoute, routePath } from "./routes.js";

// page: the element pages render into; who: the signed-in label; signOut: its button
export function startRouter({ page, who, signOut }) {
  let leaving = [];
  const ctx = {
    page,
    route: () => route(),
    onLeave: (fn) => leaving.push(fn),
  };

  async function route() {
    for (const fn of leaving) fn();
    leaving = [];
    const session = await currentSession().catch(() => null);
    who.textContent = session ? `signed in as ${session.tenant}` : "";
    signOut.hidden = !session;
    if (!session) return signInPage(ctx);
    const where = parseRoute(location.hash);
    if (where.page === "viewer") return viewerPage(ctx, where.jobId, where.params);
    return homePage(ctx);
  }

  signOut.addEventListener("click", async () => {
    await api("DELETE", "/app/session").catch(() => null);
    location.hash = "#/";
    route();
  });

  let lastPath = routePath(location.hash);
  window.addEventListener("hashchange", () => {
    // The viewer rewrites its own parameters as the view changes; only a new path is a new page.
    const path = routePath(location.hash);
    if (path !== lastPath) {
      lastPath = path;
      route();
    }
  });
  route();
}
