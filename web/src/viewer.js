// The 3D viewer: primitives as round points sized by their scale, three colour modes, the instance list, class
// visibility, picking, boxes and the query box. The host (app, `panogs view`, offline file) gives it the scene, a
// query function and the state to start from, and is told of every state change (it keeps the URL in step).
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

export const MODES = ["camera", "semantic", "instance"];
const FLAG_NORMAL = 0;
const FLAG_DIM = 1;
const FLAG_HIDDEN = 2;
const FLAG_LIT = 3;
const SIZE_STEP = 1.25;
export const DEFAULT_SIZE = 1.5; // primitives are drawn a little larger than their radius: surfaces read closed

const SHORTCUTS = [
  ["1 / 2 / 3", "colour by camera / semantic class / instance"],
  ["m", "next colour mode"],
  ["f", "fit the scene in view"],
  ["[ / ]", "smaller / larger points"],
  ["/", "type a query"],
  ["Esc", "clear the selection and the query"],
  ["?", "show or hide this help"],
];

const VERTEX_SHADER = `
attribute vec3 rgb;
attribute float scale;
attribute float flag;
uniform float sizeFactor;
uniform float projScale;
varying vec3 vColor;
void main() {
  if (flag > 1.5 && flag < 2.5) { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); gl_PointSize = 0.0; return; }
  vec4 mv = modelViewMatrix * vec4(position, 1.0);
  gl_Position = projectionMatrix * mv;
  float size = sizeFactor * scale * 2.0 * projScale / max(-mv.z, 1e-3);
  gl_PointSize = clamp(size, 1.5, 64.0);
  vColor = flag > 0.5 && flag < 1.5 ? mix(rgb, vec3(0.16), 0.82) : rgb;
}`;

const FRAGMENT_SHADER = `
varying vec3 vColor;
void main() {
  vec2 d = gl_PointCoord - vec2(0.5);
  if (dot(d, d) > 0.25) discard;
  gl_FragColor = vec4(vColor, 1.0);
}`;

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (key === "class") node.className = value;
    // Through the CSSOM, not a style attribute: the app's Content-Security-Policy (style-src 'self') blocks those.
    else if (key === "style") node.style.cssText = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (value !== undefined && value !== null) node.setAttribute(key, value);
  }
  for (const child of children) node.append(child);
  return node;
}

function css(rgb) {
  return `rgb(${rgb[0]}, ${rgb[1]}, ${rgb[2]})`;
}

export class Viewer {
  // root: an empty element; options: { queryFn(text) -> Promise<{hits}>, state, onStateChange(state), title }
  constructor(root, options) {
    this.root = root;
    this.options = options;
    this.state = { mode: "semantic", size: DEFAULT_SIZE, hidden: [], sel: null, q: "", cam: null, ...(options.state || {}) };
    this.highlighted = new Set(); // instance ids lit now (hover, selection or query hits)
    this.hits = [];
    this.boxes = [];
    this.hover = null;
    this._buildDom();
  }

  _buildDom() {
    this.root.classList.add("pgs-viewer");
    this.root.dataset.state = "loading";
    this.canvasBox = el("div", { class: "pgs-canvas" });
    this.progress = el("div", { class: "pgs-progress", role: "status" }, "Loading scene ...");
    this.progressBar = el("progress", { max: 1, value: 0 });
    this.progress.append(this.progressBar);
    this.modeButtons = MODES.map((mode, i) =>
      el("button", { type: "button", "data-mode": mode, title: `colour by ${mode} (${i + 1})`, onclick: () => this.setMode(mode) }, mode),
    );
    this.queryInput = el("input", { type: "search", placeholder: "query: class name or text", "aria-label": "query" });
    this.queryForm = el(
      "form",
      { class: "pgs-query", onsubmit: (e) => { e.preventDefault(); this.runQuery(this.queryInput.value); } },
      this.queryInput,
      el("button", { type: "submit" }, "Ask"),
    );
    this.queryStatus = el("div", { class: "pgs-query-status", "aria-live": "polite" });
    this.hitList = el("ol", { class: "pgs-hits" });
    this.legend = el("ul", { class: "pgs-legend", "aria-label": "classes" });
    this.instanceList = el("ul", { class: "pgs-instances", "aria-label": "instances" });
    this.summary = el("div", { class: "pgs-summary" });
    this.help = el(
      "div",
      { class: "pgs-help", hidden: "", role: "dialog", "aria-label": "keyboard shortcuts" },
      el("h2", {}, "Keyboard shortcuts"),
      el("table", {}, ...SHORTCUTS.map(([k, what]) => el("tr", {}, el("th", {}, k), el("td", {}, what)))),
      el("p", {}, "Drag to orbit, right-drag or shift-drag to pan, wheel to zoom, click a point to select its instance."),
    );
    const side = el(
      "aside",
      { class: "pgs-side" },
      this.summary,
      el("div", { class: "pgs-modes", role: "group", "aria-label": "colour mode" }, ...this.modeButtons),
      el(
        "div",
        { class: "pgs-tools" },
        el("button", { type: "button", "data-action": "fit", title: "fit the scene (f)", onclick: () => this.fit() }, "Fit"),
        el("button", { type: "button", title: "smaller points ([)", onclick: () => this.setSize(this.state.size / SIZE_STEP) }, "−"),
        el("button", { type: "button", title: "larger points (])", onclick: () => this.setSize(this.state.size * SIZE_STEP) }, "+"),
        el("button", { type: "button", title: "keyboard shortcuts (?)", onclick: () => this.toggleHelp() }, "?"),
      ),
      this.queryForm,
      this.queryStatus,
      this.hitList,
      el("h3", {}, "Classes"),
      this.legend,
      el("h3", {}, "Instances"),
      this.instanceList,
    );
    this.root.append(this.canvasBox, side, this.progress, this.help);
  }

  showProgress(received, total) {
    const mb = (n) => (n / 1e6).toFixed(1);
    this.progressBar.value = total ? received / total : 0;
    this.progress.firstChild.textContent = total
      ? `Loading scene ${Math.round((100 * received) / total)}% (${mb(received)} of ${mb(total)} MB)`
      : `Loading scene (${mb(received)} MB)`;
  }

  showError(message) {
    this.root.dataset.state = "error";
    this.progress.classList.add("pgs-error");
    this.progress.textContent = message;
  }

  // scene: the parsed binary scene (scene.js)
  load(scene) {
    this.scene = scene;
    const { header } = scene;
    const n = header.count;
    this.classColors = header.classes.map((c) => c.color);
    this.voidColor = header.void.color;
    let maxId = 0;
    for (const inst of header.instances) maxId = Math.max(maxId, inst.id);
    this.instanceById = new Map(header.instances.map((inst) => [inst.id, inst]));
    this.instanceLut = new Uint8Array((maxId + 1) * 3);
    for (const inst of header.instances) this.instanceLut.set(inst.color, inst.id * 3);

    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(scene.position, 3));
    this.rgb = new Uint8Array(n * 3);
    this.flags = new Uint8Array(n);
    geometry.setAttribute("rgb", new THREE.BufferAttribute(this.rgb, 3, true));
    geometry.setAttribute("scale", new THREE.BufferAttribute(scene.scale, 1));
    geometry.setAttribute("flag", new THREE.BufferAttribute(this.flags, 1));
    geometry.computeBoundingSphere();
    this.geometry = geometry;
    this.material = new THREE.ShaderMaterial({
      uniforms: { sizeFactor: { value: this.state.size }, projScale: { value: 1 } },
      vertexShader: VERTEX_SHADER,
      fragmentShader: FRAGMENT_SHADER,
    });
    this.points = new THREE.Points(geometry, this.material);

    this.renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setClearColor(0x101418);
    this.canvasBox.append(this.renderer.domElement);
    this.three = new THREE.Scene();
    this.three.add(this.points);
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.01, 1000);
    this.camera.up.set(0, 0, 1); // captures are z-up
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    this.controls.addEventListener("end", () => this._saveCamera());
    this.raycaster = new THREE.Raycaster();
    this.pickRadius = this._medianScale() * 2;

    this._fillLegend();
    this._fillInstances();
    this.summary.textContent = `${header.title ? header.title + ": " : ""}${n.toLocaleString()} primitives${
      header.total > n ? ` (of ${header.total.toLocaleString()}, decimated)` : ""
    }, ${header.instances.length} instances`;
    this._bindInput();
    new ResizeObserver(() => this._resize()).observe(this.canvasBox);
    this._resize();
    if (this.state.cam) this._restoreCamera(this.state.cam);
    else this.fit(false);
    this.setMode(this.state.mode, false);
    if (this.state.sel !== null && this.instanceById.has(this.state.sel)) this.select(this.state.sel, false);
    this.progress.hidden = true;
    this.root.dataset.state = "ready";
    if (this.state.q) this.runQuery(this.state.q);
    this.render();
  }

  _medianScale() {
    const s = this.scene.scale;
    const sample = [];
    const step = Math.max(1, Math.floor(s.length / 1000));
    for (let i = 0; i < s.length; i += step) sample.push(s[i]);
    sample.sort((a, b) => a - b);
    return sample.length ? sample[sample.length >> 1] : 0.01;
  }

  _resize() {
    const w = this.canvasBox.clientWidth || 1;
    const h = this.canvasBox.clientHeight || 1;
    this.renderer.setSize(w, h);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    const pixelHeight = h * this.renderer.getPixelRatio();
    this.material.uniforms.projScale.value = pixelHeight / (2 * Math.tan((this.camera.fov * Math.PI) / 360));
    this.render();
  }

  render() {
    if (!this.renderer) return;
    if (!this._frame) {
      this._frame = requestAnimationFrame(() => {
        this._frame = null;
        this.renderer.render(this.three, this.camera);
      });
    }
  }

  // Draw now (tests and benchmarks read pixels right after).
  renderNow() {
    this.renderer.render(this.three, this.camera);
  }

  _changed() {
    if (this.options.onStateChange) this.options.onStateChange({ ...this.state });
  }

  fit(save = true) {
    const { min, max } = this.scene.header.bounds;
    const center = new THREE.Vector3((min[0] + max[0]) / 2, (min[1] + max[1]) / 2, (min[2] + max[2]) / 2);
    const radius = Math.max(0.1, new THREE.Vector3(...max).distanceTo(new THREE.Vector3(...min)) / 2);
    const distance = radius / Math.sin((this.camera.fov * Math.PI) / 360);
    const direction = new THREE.Vector3(-0.6, -1.0, 0.8).normalize();
    this.camera.position.copy(center).addScaledVector(direction, distance);
    this.camera.near = distance / 100;
    this.camera.far = distance * 10;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(center);
    this.controls.update();
    if (save) this._saveCamera();
    this.render();
  }

  _saveCamera() {
    const p = this.camera.position;
    const t = this.controls.target;
    this.state.cam = [p.x, p.y, p.z, t.x, t.y, t.z].map((v) => Number(v.toFixed(3)));
    this._changed();
  }

  _restoreCamera(cam) {
    this.fit(false); // near/far from the scene's size
    this.camera.position.set(cam[0], cam[1], cam[2]);
    this.controls.target.set(cam[3], cam[4], cam[5]);
    this.controls.update();
  }

  setMode(mode, notify = true) {
    if (!MODES.includes(mode)) mode = "semantic";
    this.state.mode = mode;
    for (const b of this.modeButtons) b.setAttribute("aria-pressed", String(b.dataset.mode === mode));
    this.root.dataset.mode = mode;
    this._recolor();
    if (notify) this._changed();
  }

  setSize(size) {
    this.state.size = Math.min(16, Math.max(1 / 16, size));
    this.material.uniforms.sizeFactor.value = this.state.size;
    this.render();
    this._changed();
  }

  _recolor() {
    const { color, semantic, instance } = this.scene;
    const rgb = this.rgb;
    const n = this.scene.header.count;
    if (this.state.mode === "camera") {
      rgb.set(color);
    } else if (this.state.mode === "semantic") {
      const lut = new Uint8Array((this.classColors.length + 1) * 3);
      lut.set(this.voidColor, 0);
      this.classColors.forEach((c, i) => lut.set(c, (i + 1) * 3));
      for (let i = 0; i < n; i++) {
        const k = (semantic[i] + 1) * 3;
        rgb[i * 3] = lut[k];
        rgb[i * 3 + 1] = lut[k + 1];
        rgb[i * 3 + 2] = lut[k + 2];
      }
    } else {
      const lut = this.instanceLut;
      for (let i = 0; i < n; i++) {
        const id = instance[i];
        if (id < 0 || id * 3 >= lut.length) {
          rgb[i * 3] = rgb[i * 3 + 1] = rgb[i * 3 + 2] = this.voidColor[0];
        } else {
          rgb[i * 3] = lut[id * 3];
          rgb[i * 3 + 1] = lut[id * 3 + 1];
          rgb[i * 3 + 2] = lut[id * 3 + 2];
        }
      }
    }
    this.geometry.attributes.rgb.needsUpdate = true;
    this.render();
  }

  // Flags from the hidden classes and the lit instances: hidden points vanish, others dim while something is lit.
  _reflag() {
    const { semantic, instance } = this.scene;
    const n = this.scene.header.count;
    const hidden = new Uint8Array(this.classColors.length + 1);
    for (const c of this.state.hidden) if (c >= -1 && c < this.classColors.length) hidden[c + 1] = 1;
    const lit = this.highlighted;
    const anyLit = lit.size > 0;
    const flags = this.flags;
    for (let i = 0; i < n; i++) {
      if (hidden[semantic[i] + 1]) flags[i] = FLAG_HIDDEN;
      else if (!anyLit) flags[i] = FLAG_NORMAL;
      else flags[i] = lit.has(instance[i]) ? FLAG_LIT : FLAG_DIM;
    }
    this.geometry.attributes.flag.needsUpdate = true;
    this._drawBoxes();
    this.root.dataset.lit = [...lit].sort((a, b) => a - b).join(",");
    this.render();
  }

  _drawBoxes() {
    for (const box of this.boxes) this.three.remove(box);
    this.boxes = [];
    const ids = this.hover !== null ? [this.hover] : [...this.highlighted];
    for (const id of ids) {
      const inst = this.instanceById.get(id);
      if (!inst) continue;
      const box = new THREE.Box3(new THREE.Vector3(...inst.bbox_min), new THREE.Vector3(...inst.bbox_max));
      const helper = new THREE.Box3Helper(box, new THREE.Color(...inst.color.map((v) => v / 255)));
      this.boxes.push(helper);
      this.three.add(helper);
    }
  }

  _light(ids) {
    this.highlighted = new Set(ids);
    for (const row of this.instanceList.children) {
      row.classList.toggle("pgs-lit", this.highlighted.has(Number(row.dataset.instanceId)));
    }
    this._reflag();
  }

  // Select one instance (click in the list, a hit or the scene); null clears. A hit keeps the query's ranking.
  select(id, notify = true, keepHits = false) {
    this.state.sel = id;
    if (!keepHits) {
      this.hits = [];
      this.hitList.replaceChildren();
      this.queryStatus.textContent = "";
      this.state.q = "";
    }
    this._light(id === null ? [] : [id]);
    if (id !== null) {
      const row = this.instanceList.querySelector(`[data-instance-id="${id}"]`);
      if (row) row.scrollIntoView({ block: "nearest" });
    }
    if (notify) this._changed();
  }

  _preview(id) {
    this.hover = id;
    if (id === null) this._reflag();
    else {
      const saved = this.highlighted;
      this.highlighted = new Set([id]);
      this._reflag();
      this.highlighted = saved;
    }
  }

  toggleClass(index, visible) {
    const hidden = new Set(this.state.hidden);
    if (visible) hidden.delete(index);
    else hidden.add(index);
    this.state.hidden = [...hidden].sort((a, b) => a - b);
    this._reflag();
    this._changed();
  }

  async runQuery(text) {
    text = (text || "").trim();
    this.queryInput.value = text;
    if (!text) return this.clear();
    this.queryStatus.textContent = `asking "${text}" ...`;
    this.root.dataset.query = "running";
    let answer;
    try {
      answer = await this.options.queryFn(text);
    } catch (err) {
      this.queryStatus.textContent = err.message;
      this.root.dataset.query = "error";
      return;
    }
    this.state.q = text;
    this.state.sel = null;
    this.hits = answer.hits;
    this.hitList.replaceChildren(
      ...answer.hits.map((hit) =>
        el(
          "li",
          {
            "data-hit-id": hit.instance_id,
            onclick: () => this.select(hit.instance_id, true, true),
            onmouseenter: () => this._preview(hit.instance_id),
            onmouseleave: () => this._preview(null),
          },
          el("span", { class: "pgs-swatch", style: `background:${css(this.instanceById.get(hit.instance_id)?.color || [0, 0, 0])}` }),
          `#${hit.instance_id} ${hit.class_name} `,
          el("span", { class: "pgs-score" }, hit.score.toFixed(3)),
        ),
      ),
    );
    this.queryStatus.textContent = `${answer.hits.length} hit${answer.hits.length === 1 ? "" : "s"} for "${text}"`;
    this._light(answer.hits.map((h) => h.instance_id));
    this.root.dataset.query = "done";
    this._changed();
  }

  clear() {
    this.queryInput.value = "";
    this.select(null);
  }

  _fillLegend() {
    const rows = this.scene.header.classes
      .filter((c) => c.count > 0)
      .map((c) => this._legendRow(c.index, c.name, c.kind, c.color, c.count));
    if (this.scene.header.void.count > 0) {
      const v = this.scene.header.void;
      rows.push(this._legendRow(-1, "(void)", "", v.color, v.count));
    }
    this.legend.replaceChildren(...rows);
  }

  _legendRow(index, name, kind, color, count) {
    const box = el("input", { type: "checkbox", "aria-label": `show ${name}` });
    box.checked = !this.state.hidden.includes(index);
    box.addEventListener("change", () => this.toggleClass(index, box.checked));
    return el(
      "li",
      { "data-class-index": index },
      el("label", {}, box, el("span", { class: "pgs-swatch", style: `background:${css(color)}` }), ` ${name} `),
      el("span", { class: "pgs-kind" }, kind),
      el("span", { class: "pgs-count" }, count.toLocaleString()),
    );
  }

  _fillInstances() {
    const rows = [...this.scene.header.instances]
      .sort((a, b) => a.class_name.localeCompare(b.class_name) || a.id - b.id)
      .map((inst) => {
        const size = inst.bbox_max.map((v, i) => (v - inst.bbox_min[i]).toFixed(2)).join("×");
        return el(
          "li",
          {
            "data-instance-id": inst.id,
            tabindex: "0",
            title: `${inst.num_points} primitives, box ${size} m`,
            onclick: () => this.select(this.state.sel === inst.id ? null : inst.id),
            onkeydown: (e) => { if (e.key === "Enter") this.select(inst.id); },
            onmouseenter: () => this._preview(inst.id),
            onmouseleave: () => this._preview(null),
          },
          el("span", { class: "pgs-swatch", style: `background:${css(inst.color)}` }),
          ` #${inst.id} ${inst.class_name} `,
          el("span", { class: "pgs-kind" }, inst.kind),
          el("span", { class: "pgs-score" }, inst.score.toFixed(2)),
          el("span", { class: "pgs-count" }, `${inst.num_points}`),
        );
      });
    this.instanceList.replaceChildren(...rows);
  }

  _bindInput() {
    const canvas = this.renderer.domElement;
    let down = null;
    canvas.addEventListener("pointerdown", (e) => (down = [e.clientX, e.clientY]));
    canvas.addEventListener("pointerup", (e) => {
      if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 4) this.pickAt(e.clientX, e.clientY);
      down = null;
    });
    this._onKey = (e) => this._key(e);
    window.addEventListener("keydown", this._onKey);
  }

  // Select the instance of the nearest visible primitive under the pointer (client pixel coordinates).
  pickAt(clientX, clientY) {
    const rect = this.renderer.domElement.getBoundingClientRect();
    const ndc = new THREE.Vector2(((clientX - rect.left) / rect.width) * 2 - 1, -((clientY - rect.top) / rect.height) * 2 + 1);
    this.raycaster.setFromCamera(ndc, this.camera);
    this.raycaster.params.Points.threshold = this.pickRadius;
    const hits = this.raycaster.intersectObject(this.points);
    const hit = hits.find((h) => this.flags[h.index] !== FLAG_HIDDEN && this.scene.instance[h.index] >= 0);
    this.select(hit ? this.scene.instance[hit.index] : null);
    return this.state.sel;
  }

  toggleHelp(show) {
    this.help.hidden = show === undefined ? !this.help.hidden : !show;
  }

  _key(e) {
    if (e.target instanceof HTMLInputElement || e.target instanceof HTMLTextAreaElement) {
      if (e.key === "Escape") e.target.blur();
      return;
    }
    if (!this.root.isConnected || this.root.dataset.state !== "ready") return;
    const actions = {
      1: () => this.setMode("camera"),
      2: () => this.setMode("semantic"),
      3: () => this.setMode("instance"),
      m: () => this.setMode(MODES[(MODES.indexOf(this.state.mode) + 1) % MODES.length]),
      f: () => this.fit(),
      "[": () => this.setSize(this.state.size / SIZE_STEP),
      "]": () => this.setSize(this.state.size * SIZE_STEP),
      "/": () => this.queryInput.focus(),
      "?": () => this.toggleHelp(),
      Escape: () => { this.toggleHelp(false); this.clear(); },
    };
    const action = actions[e.key];
    if (action && !e.ctrlKey && !e.metaKey && !e.altKey) {
      e.preventDefault();
      action();
    }
  }

  dispose() {
    window.removeEventListener("keydown", this._onKey);
    if (this.renderer) {
      this.renderer.dispose();
      this.geometry.dispose();
      this.material.dispose();
    }
    this.root.replaceChildren();
  }
}

// The view state <-> URL hash parameters (mode, size, hidden classes, selection, query, camera).
export function stateToParams(state, params = new URLSearchParams()) {
  params.set("mode", state.mode);
  if (state.size !== DEFAULT_SIZE) params.set("size", state.size.toFixed(3));
  else params.delete("size");
  for (const [key, value] of [["hidden", state.hidden.join(",")], ["sel", state.sel ?? ""], ["q", state.q], ["cam", state.cam ? state.cam.join(",") : ""]]) {
    if (value === "" || value === null) params.delete(key);
    else params.set(key, value);
  }
  return params;
}

export function paramsToState(params) {
  const state = {};
  if (params.get("mode")) state.mode = params.get("mode");
  if (params.get("size")) state.size = Number(params.get("size")) || DEFAULT_SIZE;
  if (params.get("hidden")) state.hidden = params.get("hidden").split(",").map(Number).filter(Number.isFinite);
  if (params.get("sel")) state.sel = Number(params.get("sel"));
  if (params.get("q")) state.q = params.get("q");
  const cam = (params.get("cam") || "").split(",").map(Number);
  if (cam.length === 6 && cam.every(Number.isFinite)) state.cam = cam;
  return state;
}
