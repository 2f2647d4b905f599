// The three.js side of the viewer: the primitives as round points sized by their radius, the camera and its orbit
// controls, instance boxes, picking. Colours and flags come from colours.js; this module only uploads them.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { FLAG, flagPoints, paintPoints } from "./colours.js";
import { medianScale } from "./describe.js";

// flag (colours.js FLAG): 2 hidden (moved off screen), 1 dimmed towards grey, 0 and 3 their own colour.
// Over the photo (photo > 0.5: the splats drawn first): lit points opaque, the others at overlayAlpha when an
// overlay shows (overlayAlpha > 0), dimmed and plain points off otherwise, so the photo shows around what is lit.
const VERTEX_SHADER = `
attribute vec3 rgb;
attribute float scale;
attribute float flag;
uniform float sizeFactor;
uniform float projScale;
uniform float photo;
uniform float overlayAlpha;
varying vec3 vColor;
varying float vAlpha;
void main() {
  bool lit = flag > 2.5;
  bool off = (flag > 1.5 && flag < 2.5) || (photo > 0.5 && !lit && (flag > 0.5 || overlayAlpha <= 0.0));
  if (off) { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); gl_PointSize = 0.0; return; }
  vec4 mv = modelViewMatrix * vec4(position, 1.0);
  gl_Position = projectionMatrix * mv;
  float size = sizeFactor * scale * 2.0 * projScale / max(-mv.z, 1e-3);
  gl_PointSize = clamp(size, 1.5, 64.0);
  vColor = flag > 0.5 && flag < 1.5 ? mix(rgb, vec3(0.16), 0.82) : rgb;
  vAlpha = photo > 0.5 && !lit ? overlayAlpha : 1.0;
}`;

const FRAGMENT_SHADER = `
varying vec3 vColor;
varying float vAlpha;
void main() {
  vec2 d = gl_PointCoord - vec2(0.5);
  if (dot(d, d) > 0.25) discard;
  gl_FragColor = vec4(vColor, vAlpha);
}`;

export const OVERLAY_ALPHA = 0.45; // the class or instance colours over the photo

const BACKGROUND = 0x101418;
// From above, front left, in a z-up world; turned with the run's up (fitDirection) for any other. The first view of
// a run whose capture cameras agree on a side looks from behind them instead (first-view.js, setCaptureDirection).
const FIT_DIRECTION = new THREE.Vector3(-0.6, -1.0, 0.8).normalize();
const FOV_DEG = 50; // the orbit view's vertical field of view (a capture frame's view takes the frame's own)
const Z_UP = new THREE.Vector3(0, 0, 1); // a run that states no up (older runs) is taken as z-up
const THREE_UP = new THREE.Vector3(0, 1, 0); // the axis OrbitControls orbits about, once turned by its quaternion

// The run's up (scene header "up", from cameras.json) as a unit vector; z for a missing or degenerate one.
export function sceneUp(header) {
  const up = Array.isArray(header?.up) && header.up.length === 3 ? new THREE.Vector3(...header.up) : null;
  if (!up || !Number.isFinite(up.length()) || up.length() < 1e-9) return Z_UP.clone();
  return up.normalize();
}

export class PointsLayer {
  // container: the element the canvas fills; scene: the parsed binary scene (scene.js); size: the size factor;
  // onCameraEnd(): an orbit, pan or zoom has ended
  constructor(container, scene, size, onCameraEnd) {
    this.container = container;
    this.scene = scene;
    const n = scene.header.count;
    this.rgb = new Uint8Array(n * 3);
    this.flags = new Uint8Array(n);
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(scene.position, 3));
    geometry.setAttribute("rgb", new THREE.BufferAttribute(this.rgb, 3, true));
    geometry.setAttribute("scale", new THREE.BufferAttribute(scene.scale, 1));
    geometry.setAttribute("flag", new THREE.BufferAttribute(this.flags, 1));
    geometry.computeBoundingSphere();
    this.geometry = geometry;
    this.material = new THREE.ShaderMaterial({
      uniforms: {
        sizeFactor: { value: size },
        projScale: { value: 1 },
        photo: { value: 0 },
        overlayAlpha: { value: 0 },
      },
      vertexShader: VERTEX_SHADER,
      fragmentShader: FRAGMENT_SHADER,
    });
    this.points = new THREE.Points(geometry, this.material);
    this.points.renderOrder = 1; // over the photo's splats
    this.looping = false;

    this.renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setClearColor(BACKGROUND);
    container.append(this.renderer.domElement);
    this.three = new THREE.Scene();
    this.three.add(this.points);
    this.camera = new THREE.PerspectiveCamera(FOV_DEG, 1, 0.01, 1000);
    this.up = sceneUp(scene.header);
    this.captureDirection = null; // from the capture's cameras, once its host's cameras.json is read
    this.camera.up.copy(this.up);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement); // orbits about camera.up, as now
    this.controls.addEventListener("change", () => this.render());
    this.controls.addEventListener("end", onCameraEnd);
    this.raycaster = new THREE.Raycaster();
    this.pickRadius = medianScale(scene.scale) * 2;
    this.boxes = [];
    this.frame = null;
    this.resizeObserver = new ResizeObserver(() => this.resize());
    this.resizeObserver.observe(container);
    this.resize();
  }

  get canvas() {
    return this.renderer.domElement;
  }

  resize() {
    const w = this.container.clientWidth || 1;
    const h = this.container.clientHeight || 1;
    this.renderer.setSize(w, h);
    this.camera.aspect = w / h;
    this.updateProjection();
  }

  updateProjection() {
    this.camera.updateProjectionMatrix();
    // Pixels per unit of size at distance 1: points keep their size in metres whatever the canvas height.
    const pixelHeight = (this.container.clientHeight || 1) * this.renderer.getPixelRatio();
    this.material.uniforms.projScale.value = pixelHeight / (2 * Math.tan((this.camera.fov * Math.PI) / 360));
    this.render();
  }

  // Draw on the next animation frame, once however many changes come before it.
  render() {
    if (!this.frame) {
      this.frame = requestAnimationFrame(() => {
        this.frame = null;
        this.renderer.render(this.three, this.camera);
      });
    }
  }

  renderNow() {
    this.renderer.render(this.three, this.camera);
  }

  // The photo under the points: overlayAlpha 0 shows only the lit points over it. While it shows, every frame is
  // drawn (the splats' depth order is sorted in a worker and arrives frames later).
  setPhoto(on, overlayAlpha) {
    const u = this.material.uniforms;
    u.photo.value = on ? 1 : 0;
    u.overlayAlpha.value = overlayAlpha;
    this.material.transparent = on;
    this.material.depthWrite = !on;
    this.material.needsUpdate = true;
    this.looping = on;
    if (on) this.renderer.setAnimationLoop(() => this.renderer.render(this.three, this.camera));
    else this.renderer.setAnimationLoop(null);
    this.render();
  }

  // The run's up, when it arrives after the scene (a host's cameras.json): the fit view and the orbit's axis.
  setUp(up) {
    this.up = sceneUp({ up });
    this.camera.up.copy(this.up);
    // OrbitControls keeps the rotation from camera.up to its y axis from construction: turn it with the up.
    this.controls._quat?.setFromUnitVectors(this.up, THREE_UP);
    this.controls._quatInverse?.copy(this.controls._quat).invert();
  }

  // The direction from the scene's centre to the fit view's camera (first-view.js), or null: FIT_DIRECTION.
  setCaptureDirection(direction) {
    this.captureDirection = direction ? new THREE.Vector3(...direction).normalize() : null;
  }

  // From behind the capture's cameras where they agree on a side, else FIT_DIRECTION turned from z-up to the run's up.
  fitDirection() {
    if (this.captureDirection) return this.captureDirection.clone();
    return FIT_DIRECTION.clone().applyQuaternion(new THREE.Quaternion().setFromUnitVectors(Z_UP, this.up));
  }

  // The whole scene in view from above (of the run's up), from fitDirection; near and far planes from its size.
  fit() {
    this.camera.up.copy(this.up); // a capture frame's view may have left its own up and field of view
    this.camera.fov = FOV_DEG;
    const { min, max } = this.scene.header.bounds;
    const center = new THREE.Vector3((min[0] + max[0]) / 2, (min[1] + max[1]) / 2, (min[2] + max[2]) / 2);
    const radius = Math.max(0.1, new THREE.Vector3(...max).distanceTo(new THREE.Vector3(...min)) / 2);
    const distance = radius / Math.sin((this.camera.fov * Math.PI) / 360);
    this.camera.position.copy(center).addScaledVector(this.fitDirection(), distance);
    this.camera.near = distance / 100;
    this.camera.far = distance * 10;
    this.controls.target.copy(center);
    this.controls.update();
    this.updateProjection();
  }

  // The view of a capture frame: pose, its 4x4 T_world_cam (OpenCV camera: x right, y down, z forward);
  // camera: cameras.json's intrinsics ({fy, height}). The frame's own up (minus its y axis), so a frame held at a
  // tilt is seen at that tilt; its vertical field of view; the orbit target one metre ahead.
  lookFrom(pose, camera) {
    this.fit(); // near and far from the scene's size
    const at = (r, c) => pose[r][c];
    this.camera.position.set(at(0, 3), at(1, 3), at(2, 3));
    this.camera.up.set(-at(0, 1), -at(1, 1), -at(2, 1));
    this.controls.target.set(at(0, 3) + at(0, 2), at(1, 3) + at(1, 2), at(2, 3) + at(2, 2));
    this.camera.fov = (2 * Math.atan(camera.height / (2 * camera.fy)) * 180) / Math.PI;
    this.camera.near = Math.min(this.camera.near, 0.01);
    this.controls.update();
    this.updateProjection();
  }

  // [position x, y, z, target x, y, z]
  cameraPose() {
    const p = this.camera.position;
    const t = this.controls.target;
    return [p.x, p.y, p.z, t.x, t.y, t.z];
  }

  setCameraPose(cam) {
    this.fit(); // near and far from the scene's size
    this.camera.position.set(cam[0], cam[1], cam[2]);
    this.controls.target.set(cam[3], cam[4], cam[5]);
    this.controls.update();
  }

  setSize(size) {
    this.material.uniforms.sizeFactor.value = size;
    this.render();
  }

  paint(mode) {
    paintPoints(mode, this.scene, this.rgb);
    this.geometry.attributes.rgb.needsUpdate = true;
    this.render();
  }

  // hidden: class indices; lit: instance ids drawn lit (the others dim); boxed: instance ids whose boxes show
  setFlags(hidden, lit, boxed, instanceById) {
    const { semantic, instance, header } = this.scene;
    flagPoints(semantic, instance, header.classes.length, hidden, lit, this.flags);
    this.geometry.attributes.flag.needsUpdate = true;
    this.drawBoxes(boxed, instanceById);
    this.render();
  }

  drawBoxes(ids, instanceById) {
    for (const box of this.boxes) this.three.remove(box);
    this.boxes = [];
    for (const id of ids) {
      const inst = instanceById.get(id);
      if (!inst) continue;
      const box = new THREE.Box3(new THREE.Vector3(...inst.bbox_min), new THREE.Vector3(...inst.bbox_max));
      const helper = new THREE.Box3Helper(box, new THREE.Color(...inst.color.map((v) => v / 255)));
      this.boxes.push(helper);
      this.three.add(helper);
    }
  }

  // The instance of the nearest visible, labelled primitive under a client pixel, or null.
  pick(clientX, clientY) {
    const rect = this.canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(
      ((clientX - rect.left) / rect.width) * 2 - 1,
      -((clientY - rect.top) / rect.height) * 2 + 1,
    );
    this.raycaster.setFromCamera(ndc, this.camera);
    this.raycaster.params.Points.threshold = this.pickRadius;
    const { instance } = this.scene;
    const hit = this.raycaster
      .intersectObject(this.points)
      .find((h) => this.flags[h.index] !== FLAG.HIDDEN && instance[h.index] >= 0);
    return hit ? instance[hit.index] : null;
  }

  dispose() {
    this.renderer.setAnimationLoop(null);
    this.resizeObserver.disconnect();
    if (this.frame) cancelAnimationFrame(this.frame);
    this.controls.dispose();
    this.renderer.dispose();
    this.geometry.dispose();
    this.material.dispose();
  }
}
