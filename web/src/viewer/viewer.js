// The 3D viewer: primitives as round points sized by their scale, three colour modes, the instance list, class
// visibility, picking, boxes and the query box. The host (app, `panogs view`, offline file) gives it the scene, a
// query function and the state to start from, and is told of every state change (it keeps the URL in step).
//
// This class wires the parts: ViewState owns the state, Panels the DOM around the canvas, PointsLayer the
// three.js scene, input.js the pointer and keys. Every change goes state first, then what shows it.
import { captureViewDirection } from "./first-view.js";
import { bindClicks, bindKeys } from "./input.js";
import { Panels } from "./panels.js";
import { OVERLAY_ALPHA, PointsLayer } from "./points-layer.js";
import { summaryText } from "./describe.js";
import { SIZE_STEP, ViewState, nextMode } from "./state.js";

export class Viewer {
  // root: an empty element; options: { queryFn(text, {min_score}) -> Promise<{hits, candidates, min_score}>, state,
  // onStateChange(state), photo?, canAsk? }
  // photo: { load() -> Promise<photo.js module>, bytes() -> Promise<Uint8Array of gaussians.ply> }, given by a
  // host that has a fitted scene (or later, by offerPhoto, once the fit ends); without it the photo view is
  // unavailable. canAsk (default true): the host answers any threshold (the offline file answers stored ones).
  // cameras?: () -> Promise<cameras.json of the run> ({camera, up?, frames: [{id, T_world_cam, skipped?}]}): the
  // "look from" list, and the run's up when the scene's header has none.
  constructor(root, options) {
    this.root = root;
    this.options = options;
    this.store = new ViewState(options.state || {}, options.onStateChange);
    this.panels = new Panels(
      root,
      {
        command: (name) => this.command(name),
        query: (text) => this.runQuery(text),
        threshold: (value) => this.setMinScore(value),
        frame: (id) => this.lookFromFrame(id),
        select: (id, keepQuery) => this.select(id, true, keepQuery),
        toggle: (id) => this.select(this.state.sel === id ? null : id),
        preview: (id) => this.preview(id),
        classVisible: (index, visible) => this.toggleClass(index, visible),
      },
      options.canAsk !== false,
    );
    this.layer = null; // once a scene is loaded
    this.ready = false;
    this.photo = null; // the splats, once loaded (photo.js)
    this.photoOn = false;
    this.cameras = null; // cameras.json, once read
    this.unbind = [];
  }

  // What the host, the tests and the benchmarks read.
  get state() {
    return this.store.value;
  }
  get renderer() {
    return this.layer?.renderer;
  }
  get camera() {
    return this.layer?.camera;
  }
  get boxes() {
    return this.layer ? this.layer.boxes : [];
  }

  showProgress(received, total) {
    this.panels.showProgress(received, total);
  }

  showError(message) {
    this.panels.showError(message);
  }

  // scene: the parsed binary scene (scene.js)
  load(scene) {
    this.scene = scene;
    const { header } = scene;
    this.instanceById = new Map(header.instances.map((inst) => [inst.id, inst]));
    this.layer = new PointsLayer(this.panels.canvasBox, scene, this.state.size, () => this.saveCamera());
    this.panels.fillLegend(header, (index) => this.store.isClassHidden(index));
    this.panels.fillInstances(header.instances);
    this.panels.showSummary(summaryText(header));
    this.unbind.push(
      bindClicks(this.layer.canvas, (x, y) => this.pickAt(x, y)),
      bindKeys(
        window,
        () => this.ready && this.root.isConnected,
        (name) => this.command(name),
      ),
    );
    if (this.state.cam) this.layer.setCameraPose(this.state.cam);
    else this.layer.fit();
    this.loadFrames();
    this.setMode(this.state.mode, false);
    if (this.state.sel !== null && this.instanceById.has(this.state.sel)) this.select(this.state.sel, false);
    this.panels.setThreshold(this.state.minScore);
    this.panels.showPhoto(this.options.photo ? "off" : "unavailable");
    this.panels.showReady();
    this.ready = true;
    if (this.state.q) this.runQuery(this.state.q);
    if (this.state.photo && this.options.photo) this.togglePhoto(true);
    this.render();
  }

  // The fit ended after the viewer opened (the host watched the job): the photo view is offered from now on, and
  // opened when the URL asked for it.
  offerPhoto(photo) {
    if (this.options.photo) return;
    this.options.photo = photo;
    if (!this.layer) return; // load() offers it
    this.panels.showPhoto("off");
    if (this.state.photo) this.togglePhoto(true);
  }

  // A button's or a key's command (keys.js).
  command(name) {
    if (name.startsWith("mode:")) {
      const mode = name.slice("mode:".length);
      this.setMode(mode === "next" ? nextMode(this.state.mode) : mode);
    } else if (name === "fit") this.fit();
    else if (name === "smaller") this.setSize(this.state.size / SIZE_STEP);
    else if (name === "larger") this.setSize(this.state.size * SIZE_STEP);
    else if (name === "query") this.panels.focusQuery();
    else if (name === "help") this.toggleHelp();
    else if (name === "photo") this.togglePhoto();
    else if (name === "escape") {
      this.toggleHelp(false);
      this.clear();
    }
  }

  render() {
    if (this.layer) this.layer.render();
  }

  // Draw now (tests and benchmarks read pixels right after).
  renderNow() {
    this.layer.renderNow();
  }

  fit(save = true) {
    this.layer.fit();
    if (save) this.saveCamera();
  }

  // An orbit, pan, zoom or fit: the view is no longer a capture frame's.
  saveCamera(frame = null) {
    this.store.setCamera(this.layer.cameraPose());
    this.store.setFrame(frame);
    this.panels.showFrame(frame);
    this.store.changed();
  }

  // The capture frames' list, from the host's cameras.json; the URL's frame looked from once it is read.
  async loadFrames() {
    if (!this.options.cameras) return;
    try {
      this.cameras = await this.options.cameras();
    } catch (_) {
      return; // no list: the orbit view only
    }
    if (this.layer) {
      if (Array.isArray(this.cameras.up) && !this.scene.header.up) this.layer.setUp(this.cameras.up); // upright
      // The first view from behind the capture's cameras, looking their way (where they agree on a side), unless
      // the URL placed the camera or the user moved it while the list was read.
      this.layer.setCaptureDirection(captureViewDirection(this.cameras.frames, this.layer.up.toArray()));
      if (!this.state.cam && this.state.frame === null) this.fit(false);
    }
    const ids = this.cameras.frames.map((frame) => String(frame.id));
    const skipped = new Set(this.cameras.frames.filter((f) => f.skipped).map((f) => String(f.id)));
    this.panels.fillFrames(ids, this.state.frame, skipped);
    if (this.state.frame !== null && ids.includes(this.state.frame)) this.lookFromFrame(this.state.frame);
  }

  // The camera at a capture frame's pose and field of view ("" or an unknown id: nothing changes).
  lookFromFrame(id) {
    const frame = this.cameras?.frames.find((f) => String(f.id) === String(id));
    if (!frame || !this.layer) return;
    this.layer.lookFrom(frame.T_world_cam, this.cameras.camera);
    this.saveCamera(String(frame.id));
  }

  setMode(mode, notify = true) {
    mode = this.store.setMode(mode);
    this.panels.showMode(mode);
    if (this.layer) this.layer.paint(mode);
    if (this.photoOn) this.layer.setPhoto(true, this.overlayAlpha());
    if (notify) this.store.changed();
  }

  // Over the photo: the class or instance colours, half transparent; in camera mode only the lit instances.
  overlayAlpha() {
    return this.state.mode === "camera" ? 0 : OVERLAY_ALPHA;
  }

  // The photo view on or off (show: force one); the splats are fetched and built the first time.
  async togglePhoto(show = !this.photoOn) {
    if (!this.options.photo || !this.layer) return;
    if (show && !this.photo) {
      this.panels.showPhoto("loading", "loading the Gaussian scene ...");
      try {
        const [module, bytes] = await Promise.all([this.options.photo.load(), this.options.photo.bytes()]);
        this.photo = await module.addSplats(this.layer, bytes);
      } catch (err) {
        this.panels.showPhoto("error", `photo unavailable: ${err.message}`);
        return;
      }
    }
    this.photoOn = show;
    this.photo.setVisible(show);
    this.layer.setPhoto(show, this.overlayAlpha());
    this.panels.showPhoto(show ? "on" : "off");
    this.store.setPhoto(show);
    this.store.changed();
  }

  // The query's threshold (the control beside the query box): the shown query is asked again with it.
  setMinScore(value) {
    this.panels.setThreshold(this.store.setMinScore(value));
    this.store.changed();
    if (this.state.q && this.ready) this.runQuery(this.state.q);
  }

  setSize(size) {
    size = this.store.setSize(size);
    if (this.layer) this.layer.setSize(size);
    this.store.changed();
  }

  // Flags and boxes from the hidden classes and the lit instances (lit: the preview's, else the state's).
  reflag(lit = this.store.lit) {
    if (this.layer) this.layer.setFlags(this.state.hidden, lit, this.store.boxed(), this.instanceById);
    this.panels.showLit(lit);
  }

  // Select one instance (click in the list, a hit or the scene); null clears. A hit keeps the query's ranking.
  select(id, notify = true, keepHits = false) {
    this.store.select(id, keepHits);
    if (!keepHits) this.panels.clearHits();
    this.panels.markInstances(this.store.lit);
    this.reflag();
    if (id !== null) this.panels.scrollToInstance(id);
    if (notify) this.store.changed();
  }

  // Show one instance lit while the pointer is on its row (null: back to the state's).
  preview(id) {
    this.store.setHover(id);
    this.reflag(id === null ? this.store.lit : new Set([id]));
  }

  toggleClass(index, visible) {
    this.store.setClassVisible(index, visible);
    this.reflag();
    this.store.changed();
  }

  async runQuery(text) {
    text = (text || "").trim();
    this.panels.setQueryText(text);
    if (!text) return this.clear();
    this.panels.showAsking(text);
    const asked = (this.asked = (this.asked || 0) + 1);
    let answer;
    try {
      answer = await this.options.queryFn(text, { min_score: this.state.minScore });
      if (asked !== this.asked) return; // a later question (or threshold) was asked meanwhile: its answer shows
    } catch (err) {
      if (asked !== this.asked) return;
      // Nothing of the last answer stays lit or listed under the refusal.
      this.store.answer(text, []);
      this.panels.markInstances(this.store.lit);
      this.reflag();
      this.panels.showQueryError(err.message);
      return;
    }
    this.store.answer(text, answer.hits);
    this.panels.showHits(text, answer, (id) => this.instanceById.get(id)?.color || [0, 0, 0]);
    this.panels.markInstances(this.store.lit);
    this.reflag();
    this.panels.showQueryDone();
    this.store.changed();
  }

  clear() {
    this.panels.setQueryText("");
    this.select(null);
  }

  // Select the instance of the nearest visible primitive under the pointer (client pixel coordinates).
  pickAt(clientX, clientY) {
    this.select(this.layer.pick(clientX, clientY));
    return this.state.sel;
  }

  toggleHelp(show) {
    this.panels.toggleHelp(show);
  }

  dispose() {
    for (const unbind of this.unbind) unbind();
    this.unbind = [];
    if (this.photo) this.photo.dispose();
    if (this.layer) this.layer.dispose();
    this.panels.clear();
  }
}
