// The viewer's DOM around the canvas: the side panel (summary, colour modes, tools, query box, hits, legend,
// instance list), the loading overlay and the shortcut help. It shows what it is told and reports clicks to the
// viewer; it keeps no state of its own. The root's data-* attributes (state, mode, lit, query) are what the
// browser tests and benchmarks wait on.
import { h } from "../dom.js";
import { cssRgb } from "./colours.js";
import {
  answerText,
  formatScore,
  hitScoreText,
  instanceOrder,
  instanceTitle,
  legendRows,
  progressText,
} from "./describe.js";
import { SHORTCUTS } from "./keys.js";
import { MODES } from "./state.js";

function swatch(color) {
  return h("span", { class: "pgs-swatch", style: { background: cssRgb(color) } });
}

export class Panels {
  // on: { command(name), query(text), threshold(value), frame(id), select(id, keepQuery), toggle(id), preview(id),
  //       classVisible(index, visible) }
  // canAsk: whether the host can ask again with another threshold (the offline file answers stored class queries)
  constructor(root, on, canAsk = true) {
    this.root = root;
    this.on = on;
    root.classList.add("pgs-viewer");
    root.dataset.state = "loading";
    this.canvasBox = h("div", { class: "pgs-canvas" });
    // Over the canvas while the Gaussian scene is fetched and built (seconds for a real capture).
    this.photoLoading = h(
      "div",
      { class: "pgs-photo-loading", role: "status", hidden: true },
      "loading the photo view ...",
    );
    this.progress = h("div", { class: "pgs-progress", role: "status" }, "Loading scene ...");
    this.progressBar = h("progress", { max: 1, value: 0 });
    this.progress.append(this.progressBar);
    this.modeButtons = MODES.map((mode, i) =>
      h(
        "button",
        {
          type: "button",
          "data-mode": mode,
          title: `colour by ${mode} (${i + 1})`,
          onclick: () => on.command(`mode:${mode}`),
        },
        mode,
      ),
    );
    this.queryInput = h("input", { type: "search", placeholder: "query: class name or text", "aria-label": "query" });
    const queryForm = h(
      "form",
      {
        class: "pgs-query",
        onsubmit: (e) => {
          e.preventDefault();
          on.query(this.queryInput.value);
        },
      },
      this.queryInput,
      h("button", { type: "submit" }, "Ask"),
    );
    // The score a hit reaches: lowered, a query that matched nothing well lights its closest instances.
    this.thresholdInput = h("input", {
      type: "number",
      min: 0,
      max: 1,
      step: 0.05,
      "data-role": "threshold",
      "aria-label": "minimum score of a hit",
      title: "a hit scores at least this (0.5: the query beats the other classes together)",
      onchange: () => on.threshold(this.thresholdInput.value),
    });
    const threshold = h(
      "label",
      { class: "pgs-threshold", hidden: !canAsk },
      "hits score at least ",
      this.thresholdInput,
    );
    this.queryStatus = h("div", { class: "pgs-query-status", "aria-live": "polite" });
    this.hitList = h("ol", { class: "pgs-hits" });
    this.legend = h("ul", { class: "pgs-legend", "aria-label": "classes" });
    this.instanceList = h("ul", { class: "pgs-instances", "aria-label": "instances" });
    this.summary = h("div", { class: "pgs-summary" });
    this.help = h(
      "div",
      { class: "pgs-help", hidden: true, role: "dialog", "aria-label": "keyboard shortcuts" },
      h("h2", {}, "Keyboard shortcuts"),
      h("table", {}, ...SHORTCUTS.map(([key, what]) => h("tr", {}, h("th", {}, key), h("td", {}, what)))),
      h(
        "p",
        {},
        "Drag to orbit, right-drag or shift-drag to pan, wheel to zoom, click a point to select its instance.",
      ),
    );
    const tool = (label, title, command, attrs = {}) =>
      h("button", { type: "button", title, ...attrs, onclick: () => on.command(command) }, label);
    const side = h(
      "aside",
      { class: "pgs-side" },
      this.summary,
      h("div", { class: "pgs-modes", role: "group", "aria-label": "colour mode" }, ...this.modeButtons),
      h(
        "div",
        { class: "pgs-tools" },
        tool("Fit", "fit the scene (f)", "fit", { "data-action": "fit" }),
        tool("−", "smaller points ([)", "smaller"),
        tool("+", "larger points (])", "larger"),
        tool("?", "keyboard shortcuts (?)", "help"),
      ),
      (this.photoButton = h(
        "button",
        {
          type: "button",
          class: "pgs-photo",
          "data-action": "photo",
          hidden: true,
          title: "the fitted Gaussian scene under the colours (p)",
          onclick: () => on.command("photo"),
        },
        "photo",
      )),
      (this.photoStatus = h("span", { class: "pgs-photo-status", "aria-live": "polite" })),
      (this.frameBox = h(
        "label",
        { class: "pgs-frames", hidden: true },
        "look from ",
        (this.frameSelect = h("select", {
          "data-role": "frame",
          "aria-label": "look from a capture frame",
          onchange: () => on.frame(this.frameSelect.value),
        })),
      )),
      queryForm,
      threshold,
      this.queryStatus,
      this.hitList,
      h("h3", {}, "Classes"),
      this.legend,
      h("h3", {}, "Instances"),
      this.instanceList,
    );
    root.append(this.canvasBox, side, this.progress, this.photoLoading, this.help);
  }

  showProgress(received, total) {
    this.progressBar.value = total ? received / total : 0;
    this.progress.firstChild.textContent = progressText(received, total);
  }

  showError(message) {
    this.root.dataset.state = "error";
    this.progress.classList.add("pgs-error");
    this.progress.textContent = message;
  }

  showReady() {
    this.progress.hidden = true;
    this.root.dataset.state = "ready";
  }

  // The photo toggle: "unavailable" (no fitted scene: the button stays hidden), "off", "loading", "on", "error".
  showPhoto(state, text = "") {
    this.root.dataset.photo = state;
    this.photoButton.hidden = state === "unavailable";
    this.photoButton.setAttribute("aria-pressed", String(state === "on"));
    this.photoStatus.textContent = text;
    this.photoLoading.hidden = state !== "loading";
  }

  showMode(mode) {
    for (const button of this.modeButtons) button.setAttribute("aria-pressed", String(button.dataset.mode === mode));
    this.root.dataset.mode = mode;
  }

  showSummary(text) {
    this.summary.textContent = text;
  }

  // isHidden(index): whether the class starts unticked
  fillLegend(header, isHidden) {
    const rows = legendRows(header).map(({ index, name, kind, color, count }) => {
      const box = h("input", { type: "checkbox", "aria-label": `show ${name}` });
      box.checked = !isHidden(index);
      box.addEventListener("change", () => this.on.classVisible(index, box.checked));
      return h(
        "li",
        { "data-class-index": index },
        h("label", {}, box, swatch(color), ` ${name} `),
        h("span", { class: "pgs-kind" }, kind),
        h("span", { class: "pgs-count" }, count.toLocaleString()),
      );
    });
    this.legend.replaceChildren(...rows);
  }

  fillInstances(instances) {
    const rows = instanceOrder(instances).map((inst) =>
      h(
        "li",
        {
          "data-instance-id": inst.id,
          tabindex: "0",
          title: instanceTitle(inst),
          onclick: () => this.on.toggle(inst.id),
          onkeydown: (e) => {
            if (e.key === "Enter") this.on.select(inst.id, false);
          },
          onmouseenter: () => this.on.preview(inst.id),
          onmouseleave: () => this.on.preview(null),
        },
        swatch(inst.color),
        ` #${inst.id} ${inst.class_name} `,
        h("span", { class: "pgs-kind" }, inst.kind),
        h("span", { class: "pgs-score" }, inst.score.toFixed(2)),
        h("span", { class: "pgs-count" }, `${inst.num_points}`),
      ),
    );
    this.instanceList.replaceChildren(...rows);
  }

  // The selection's or the hits' rows marked in the instance list.
  markInstances(ids) {
    for (const row of this.instanceList.children) {
      row.classList.toggle("pgs-lit", ids.has(Number(row.dataset.instanceId)));
    }
  }

  scrollToInstance(id) {
    const row = this.instanceList.querySelector(`[data-instance-id="${id}"]`);
    if (row) row.scrollIntoView({ block: "nearest" });
  }

  // The instances drawn lit, sorted, on the root (data-lit).
  showLit(ids) {
    this.root.dataset.lit = [...ids].sort((a, b) => a - b).join(",");
  }

  setQueryText(text) {
    this.queryInput.value = text;
  }

  // ids: the capture frames whose poses the run has (cameras.json), in its order; selected: the one looked from;
  // skipped: the ids of frames the import left out of the bundle (a pose only: no key frame of the run)
  fillFrames(ids, selected, skipped = new Set()) {
    const option = (value, text) => h("option", { value }, text);
    const label = (id) => (skipped.has(id) ? `frame ${id} (not in the bundle)` : `frame ${id}`);
    this.frameSelect.replaceChildren(option("", "a capture frame ..."), ...ids.map((id) => option(id, label(id))));
    this.frameSelect.value = selected ?? "";
    this.frameBox.hidden = !ids.length;
  }

  showFrame(id) {
    this.frameSelect.value = id ?? "";
  }

  setThreshold(value) {
    this.thresholdInput.value = formatScore(value);
  }

  focusQuery() {
    this.queryInput.focus();
  }

  clearHits() {
    this.hitList.replaceChildren();
    this.queryStatus.textContent = "";
  }

  showAsking(text) {
    this.queryStatus.textContent = `asking "${text}" ...`;
    this.root.dataset.query = "running";
  }

  // The refusal replaces the last answer's list: hits left under it would read as this query's.
  showQueryError(message) {
    this.hitList.replaceChildren();
    this.queryStatus.textContent = message;
    this.root.dataset.query = "error";
  }

  // answer: the server's ranking ({hits, candidates, min_score}), kept in its order; the candidates (no hits: under
  // the threshold) follow the hits, marked, unlit, with their scores. colourOf(id): an instance's colour
  showHits(text, answer, colourOf) {
    const row = (hit, below) =>
      h(
        "li",
        {
          [below ? "data-candidate-id" : "data-hit-id"]: hit.instance_id,
          class: below ? "pgs-below" : null,
          title: below ? `under the threshold (${formatScore(answer.min_score ?? 0.5)})` : null,
          onclick: () => this.on.select(hit.instance_id, true),
          onmouseenter: () => this.on.preview(hit.instance_id),
          onmouseleave: () => this.on.preview(null),
        },
        swatch(colourOf(hit.instance_id)),
        `#${hit.instance_id} ${hit.class_name} `,
        below ? h("span", { class: "pgs-kind" }, "below") : null,
        h("span", { class: "pgs-score" }, hitScoreText(hit.score)),
      );
    this.hitList.replaceChildren(
      ...answer.hits.map((hit) => row(hit, false)),
      ...(answer.candidates || []).map((hit) => row(hit, true)),
    );
    this.queryStatus.textContent = answerText(text, answer);
  }

  showQueryDone() {
    this.root.dataset.query = "done";
  }

  toggleHelp(show) {
    this.help.hidden = show === undefined ? !this.help.hidden : !show;
  }

  clear() {
    this.root.replaceChildren();
  }
}
