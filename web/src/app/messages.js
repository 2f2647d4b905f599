// A message box showing an error: its message, then the service's problems one per line (a refused bundle lists
// every problem it found).
import { h } from "../dom.js";

export function showError(box, err) {
  box.className = "pgs-message pgs-bad";
  box.replaceChildren(err.message);
  if (err.problems && err.problems.length) {
    box.append(h("ul", { class: "pgs-problems" }, ...err.problems.map((p) => h("li", {}, p))));
  }
}
