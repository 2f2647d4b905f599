// The app: sign in, upload a bundle over tus, watch jobs live, cancel, re-run, delete, open the viewer. The pages
// live under app/pages, the routes in the URL's fragment (app/routes.js).
import { startRouter } from "./app/router.js";

startRouter({
  page: document.getElementById("page"),
  who: document.getElementById("who"),
  signOut: document.getElementById("sign-out"),
});
