// The page's 3D view (docs/service.md): a model's splats, its training cameras and the ranked
// candidates as frusta, drawn with WebGL through the vendored three.js (service/page/vendor/).
// It is a client of the REST API like app.js: GET /v1/models/{id}/scene (the splats as a
// compact binary), /cameras (the training cameras, and the capture's up that the view stands
// on), and the explain job (POST /v1/models/{id}/explain) that colours the splats by coverage,
// fragility and what the first pick would newly see.
//
// Splats are point sprites: a gaussian falloff over +-2 sigma of each splat's size, alpha
// blended back to front. The points are sorted by depth (a counting sort on 16-bit keys, a few
// ms for 200k points) whenever the view has turned, not every frame: additive blending would
// need no sort but turns dense surfaces white and hides the colour the toggle is about.
//
// API, on window.phdView3d:
//   mount(element, {modelId, headers})   load and draw the model and its training cameras; resolves
//                                        to false when it cannot draw (no WebGL: its status line
//                                        says so, and the other calls do nothing) or another model
//                                        was mounted meanwhile. modelId null: no model (a capture
//                                        not trained yet shows its cameras alone)
//   showRanking(result, {candidates})    a rank result as the REST API returns it: candidates as
//                                        frusta coloured by score with their rank; `candidates`
//                                        (optional, all frames ranked) adds the unreturned, faint
//   showTargets(frames)                  the rank request's target views (where the model will be
//                                        looked at from), faint frusta in their own colour; [] for
//                                        none. Kept when another model is mounted
//   showCapture(element, capture)        a capture's rounds (GET /v1/captures/{id}) in place of the
//                                        training cameras: each round's captured cameras in its colour
//                                        of the rounds ramp, the last round's next poses; null for
//                                        none. Kept when another model is mounted (the page drops it)
//   onPick(callback(index))              a candidate frustum was clicked
//   clear()                              no ranking: its frusta and detail panel go
//   refresh()                            the model changed (calibrated): explained again for the mode shown
//   select(index)                        highlight it; show its render and heat map
//   setMode(name)                        colour | coverage | fragility | novelty
//   debug()                              the view's camera and what it drew (for tests)
import * as THREE from "./vendor/three.module.min.js";
import { OrbitControls } from "./vendor/OrbitControls.js";

const EXPLAIN_SAMPLES = 8;          // masks per view for fragility: the page's quick look, not the ranking's N
const EXPLAIN_SIDE = 160;           // explain renders at most this many pixels a side (downscaled from the frames)
const FRUSTUM_SHARE = 0.12;         // a frustum's depth, of the scene's radius
const BACKGROUND = 0x15181d;
// How each kind of frustum is drawn: wire colour and opacity, and the fill of its image rectangle.
// The legend draws its swatches from the same table, so a swatch looks like the frusta it names.
// Target views: orange, off the candidates' ramp and the cameras' greys, and faint: a capture's
// whole path (tens of frusta) lies over the training cameras and the model and must not hide them.
// A capture's rounds: round 0 at the ramp's first stop, the last round at its last (sky blue to
// violet to pink, apart from the other kinds); the poses to capture next filled, in mint.
const FRUSTA = {
  training: { rgb: [232, 236, 240], opacity: 0.75, fill: 0 },
  target: { rgb: [255, 140, 0], opacity: 0.35, fill: 0.1 },
  unreturned: { rgb: [138, 148, 160], opacity: 0.3, fill: 0 },
  round: { ramp: "rounds", opacity: 0.9, fill: 0.12 },
  next: { rgb: [60, 230, 160], opacity: 1, fill: 0.45 },
};

// Ramps: five stops each, low to high. Scores and fragility on the heat maps' ramp (viridis);
// coverage from red (no captured view saw it) to teal (seen by many); novelty grey to magenta.
const RAMPS = {
  score: [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]],
  fragility: [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]],
  coverage: [[214, 39, 40], [245, 133, 24], [240, 214, 60], [120, 198, 121], [26, 152, 160]],
  novelty: [[70, 74, 82], [105, 96, 120], [160, 90, 170], [215, 70, 200], [255, 60, 230]],
  rounds: [[90, 170, 255], [120, 140, 255], [160, 120, 250], [215, 110, 215], [255, 105, 160]],
};
const MODES = {
  colour: { label: "colour", legend: null },
  coverage: { label: "coverage", legend: ["no captured view saw it", "seen well"] },
  fragility: { label: "fragility", legend: ["stable under dropout", "fragile (zeta high)"] },
  novelty: { label: "seen by #1", legend: ["seen before (or not by #1)", "newly seen by #1"] },
};

function rampColour(name, t) {
  const stops = RAMPS[name];
  const x = Math.max(0, Math.min(1, t)) * (stops.length - 1);
  const i = Math.min(stops.length - 2, Math.floor(x));
  return stops[i].map((v, k) => Math.round(v + (stops[i + 1][k] - v) * (x - i)));
}
const css = (rgb) => `rgb(${rgb.join(",")})`;

// ------------------------------------------------------------------ shaders

const POINT_VERTEX = `
attribute float sigma;
attribute vec4 rgba;
attribute float value;
uniform float projScale;
uniform float mode;            // 0: the splat's colour; 1: value on the ramp
uniform vec3 ramp[5];
varying vec4 vColour;
vec3 onRamp(float t) {
  float x = clamp(t, 0.0, 1.0) * 4.0;
  int i = int(min(floor(x), 3.0));
  vec3 a = ramp[0], b = ramp[1];
  if (i == 1) { a = ramp[1]; b = ramp[2]; } else if (i == 2) { a = ramp[2]; b = ramp[3]; } else if (i == 3) { a = ramp[3]; b = ramp[4]; }
  return mix(a, b, x - float(i));
}
void main() {
  vec4 mv = modelViewMatrix * vec4(position, 1.0);
  gl_Position = projectionMatrix * mv;
  gl_PointSize = clamp(4.0 * sigma * projScale / max(-mv.z, 1e-4), 2.0, 64.0);   // +-2 sigma across
  if (mode < 0.5) {
    vColour = rgba;
  } else if (value > 0.999) {  // byte 255: no view shows this splat
    vColour = vec4(0.45, 0.47, 0.5, max(rgba.a, 0.15));
  } else {                     // faint splats stay faint, but not invisible
    vColour = vec4(onRamp(value * 255.0 / 254.0), max(rgba.a, 0.15));
  }
}`;

const POINT_FRAGMENT = `
varying vec4 vColour;
void main() {
  vec2 d = gl_PointCoord * 2.0 - 1.0;          // the sprite spans +-2 sigma
  float a = vColour.a * exp(-2.0 * dot(d, d)); // exp(-r^2 / 2) with r in sigma
  if (a < 1.0 / 255.0) discard;
  gl_FragColor = vec4(vColour.rgb, a);
}`;

// ------------------------------------------------------------------ small helpers

const el = (tag, attrs = {}, ...children) => {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v; else if (k === "text") node.textContent = v; else node.setAttribute(k, v);
  }
  node.append(...children);
  return node;
};

class ViewError extends Error {
  constructor(message, code = null) { super(message); this.code = code; }
}

// What the service's error codes mean to someone looking at the view (the rest: the server's message).
const PLAIN = {
  not_calibrated: "calibrate the model first: fragility is measured at its dropout ratio",
  unauthorized: "the server needs the API key",
  busy: "the server is busy: try again in a moment",
  queue_full: "the server is busy: try again in a moment",
};

async function request(path, options = {}) {
  const response = await fetch(path, { method: options.method || "GET", headers: Object.assign({}, view.headers,
    options.json ? { "Content-Type": "application/json" } : {}), body: options.json ? JSON.stringify(options.json) : undefined });
  if (!response.ok) {
    let text = `the server answered ${response.status}`, code = null;
    try { ({ message: text, code } = (await response.json()).error); } catch (_) { /* not our error shape */ }
    throw new ViewError(PLAIN[code] || text, code);
  }
  return response;
}

// A frame -> its camera-to-world matrix (OpenGL) and intrinsics: a transforms frame, or a reference
// trainer's cameras.json entry (OpenCV axes, y down and looking along +z; principal point at the centre).
function frameCamera(frame) {
  if (!frame.transform_matrix) {
    const r = frame.rotation, p = frame.position;
    const c2w = new THREE.Matrix4().set(...[0, 1, 2].flatMap((i) => [r[i][0], -r[i][1], -r[i][2], p[i]]), 0, 0, 0, 1);
    return { c2w, w: frame.width, h: frame.height, fx: frame.fx, fy: frame.fy, cx: frame.width / 2, cy: frame.height / 2 };
  }
  const m = frame.transform_matrix;
  const c2w = new THREE.Matrix4().set(...m[0], ...m[1], ...m[2], ...(m[3] || [0, 0, 0, 1]));
  const w = frame.w, h = frame.h;
  const fx = frame.fl_x ?? (frame.camera_angle_x ? 0.5 * w / Math.tan(0.5 * frame.camera_angle_x) : w);
  const fy = frame.fl_y ?? fx;
  return { c2w, w, h, fx, fy, cx: frame.cx ?? w / 2, cy: frame.cy ?? h / 2 };
}

// ------------------------------------------------------------------ the view

const view = {
  root: null, renderer: null, scene: null, camera: null, controls: null,
  headers: {}, modelId: null, header: null, points: null, positions: null, up: [0, 0, 1],
  training: [], ranking: null, frusta: [], selected: null, pickCallbacks: [], targets: [], targetFrusta: [],
  targetsShown: true, // the legend's check box: the target views' frusta drawn
  capture: null,      // the capture shown (showCapture): its rounds' frusta replace the training cameras'
  roundFrusta: [],    // [{round, rgb, frusta}] and the next poses' frusta, as drawn
  nextFrusta: [],
  mode: "colour", explained: null, explaining: null, radius: 1, centre: new THREE.Vector3(),
  sortPending: true, sortMs: null, touched: false, blobs: [],
  noWebGL: null,      // why the browser cannot draw the view, once it has failed to
};

function build(element) {
  element.replaceChildren();
  element.classList.add("view3d");
  const canvasBox = el("div", { class: "v3d-stage" });
  const labels = el("div", { class: "v3d-labels" });
  const modes = el("div", { class: "v3d-modes", role: "radiogroup", "aria-label": "colour the splats by" },
    ...Object.entries(MODES).map(([name, m]) => {
      const input = el("input", { type: "radio", name: "v3d-mode", value: name });
      if (name === view.mode) input.checked = true;
      input.addEventListener("change", () => setMode(name));
      return el("label", {}, input, document.createTextNode(" " + m.label));
    }));
  const progress = el("progress", { class: "v3d-progress", max: "1", value: "0" });
  progress.hidden = true;
  const status = el("p", { class: "v3d-status", role: "status", "aria-live": "polite" });
  const legend = el("div", { class: "v3d-legend" });
  const detail = el("div", { class: "v3d-detail" });
  detail.hidden = true;
  canvasBox.append(labels);
  element.append(el("div", { class: "v3d-bar" }, modes, progress), canvasBox, status, legend, detail);
  Object.assign(view, { root: element, stage: canvasBox, labels, status, legend, detail, progress, modes });

  let renderer;
  try {
    renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  } catch (err) {
    view.noWebGL = err.message;
    element.replaceChildren(status);          // no empty stage or colour modes: only why
    say("this browser cannot draw the 3D view: it needs WebGL (" + err.message + "); the rest of the page works " +
      "without it", true);
    return false;
  }
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  renderer.setClearColor(BACKGROUND, 1);
  canvasBox.prepend(renderer.domElement);
  const camera = new THREE.PerspectiveCamera(50, 1, 0.01, 1000);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.enableDamping = false;
  controls.addEventListener("change", () => { view.sortPending = true; draw(); });
  controls.addEventListener("start", () => { view.touched = true; });    // the user moved the view: no refit
  Object.assign(view, { renderer, camera, controls, scene: new THREE.Scene() });

  let down = null;
  renderer.domElement.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
  renderer.domElement.addEventListener("pointerup", (e) => {
    if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 5) clicked(e);
    down = null;
  });
  new ResizeObserver(() => resize()).observe(canvasBox);
  resize();
  return true;
}

function resize() {
  const width = Math.max(1, view.stage.clientWidth), height = Math.max(1, view.stage.clientHeight);
  view.renderer.setSize(width, height, false);
  view.camera.aspect = width / height;
  view.camera.updateProjectionMatrix();
  draw();
}

function say(text, isError = false) {
  view.status.textContent = text;
  view.status.classList.toggle("error", isError);
}

// ------------------------------------------------------------------ the splats

function parseScene(buffer) {
  const bytes = new Uint8Array(buffer);
  if (String.fromCharCode(...bytes.subarray(0, 4)) !== "PHD3") throw new ViewError("the scene is not in the PHD3 format");
  const length = new DataView(buffer).getUint32(4, true);
  const header = JSON.parse(new TextDecoder().decode(bytes.subarray(8, 8 + length)));
  const arrays = {};
  for (const part of header.layout) {
    const Type = part.type === "float32" ? Float32Array : Uint8Array;
    arrays[part.name] = new Type(buffer, part.offset, part.length);
  }
  return { header, arrays };
}

function makePoints({ header, arrays }) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(arrays.positions, 3));
  geometry.setAttribute("sigma", new THREE.BufferAttribute(arrays.sigma, 1));
  geometry.setAttribute("rgba", new THREE.BufferAttribute(arrays.colours, 4, true));
  geometry.setAttribute("value", new THREE.BufferAttribute(new Uint8Array(header.count), 1, true));
  geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(header.count).map((_, i) => i), 1));
  const material = new THREE.ShaderMaterial({
    vertexShader: POINT_VERTEX, fragmentShader: POINT_FRAGMENT, transparent: true, depthWrite: false,
    uniforms: { projScale: { value: 1 }, mode: { value: 0 }, ramp: { value: RAMPS.coverage.map((c) => new THREE.Vector3(...c.map((v) => v / 255))) } },
  });
  const points = new THREE.Points(geometry, material);
  points.frustumCulled = false;
  return points;
}

// Back to front along the view direction: a counting sort on 16-bit depth keys.
function sortPoints() {
  if (!view.points || !view.sortPending) return;
  view.sortPending = false;
  const started = performance.now();
  const p = view.positions, count = p.length / 3;
  const forward = new THREE.Vector3();
  view.camera.getWorldDirection(forward);
  const eye = view.camera.position;
  const depth = new Float32Array(count);
  let lo = Infinity, hi = -Infinity;
  for (let i = 0; i < count; i++) {
    const d = (p[3 * i] - eye.x) * forward.x + (p[3 * i + 1] - eye.y) * forward.y + (p[3 * i + 2] - eye.z) * forward.z;
    depth[i] = d;
    if (d < lo) lo = d;
    if (d > hi) hi = d;
  }
  const scale = hi > lo ? 65535 / (hi - lo) : 0;
  const keys = new Uint16Array(count);
  const counts = new Uint32Array(65537);
  for (let i = 0; i < count; i++) { keys[i] = 65535 - Math.floor((depth[i] - lo) * scale); counts[keys[i] + 1]++; }
  for (let k = 1; k <= 65536; k++) counts[k] += counts[k - 1];
  const index = view.points.geometry.index;
  const order = index.array;
  for (let i = 0; i < count; i++) order[counts[keys[i]]++] = i;   // far (key 0) first
  index.needsUpdate = true;
  view.sortMs = performance.now() - started;
}

// ------------------------------------------------------------------ frusta

function frustum(frame, colour, { fill = 0, opacity = 1, order = 1 } = {}) {   // colour: a THREE.Color
  const cam = frameCamera(frame);
  const d = FRUSTUM_SHARE * view.radius;
  // Image corners at depth d, camera space (OpenGL: x right, y up, looking along -z).
  const x0 = -cam.cx / cam.fx * d, x1 = (cam.w - cam.cx) / cam.fx * d;
  const y0 = -(cam.h - cam.cy) / cam.fy * d, y1 = cam.cy / cam.fy * d;
  const corners = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]].map(([x, y]) => new THREE.Vector3(x, y, -d));
  const apex = new THREE.Vector3(0, 0, 0);
  const top = new THREE.Vector3((x0 + x1) / 2, y1 + 0.25 * (y1 - y0), -d);   // the up mark
  const lines = [];
  for (const c of corners) lines.push(apex, c);
  for (let i = 0; i < 4; i++) lines.push(corners[i], corners[(i + 1) % 4]);
  lines.push(corners[3], top, top, corners[2]);
  const group = new THREE.Group();
  const material = new THREE.LineBasicMaterial({ color: colour, transparent: opacity < 1, opacity, depthTest: false });
  const wire = new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(lines), material);
  wire.renderOrder = order;
  group.add(wire);
  let quad = null;
  if (fill > 0) {
    const shape = new THREE.BufferGeometry().setFromPoints([corners[0], corners[1], corners[2], corners[0], corners[2], corners[3]]);
    quad = new THREE.Mesh(shape, new THREE.MeshBasicMaterial({ color: colour, transparent: true, opacity: fill,
      side: THREE.DoubleSide, depthTest: false }));
    quad.renderOrder = order;
    group.add(quad);
  }
  group.applyMatrix4(cam.c2w);
  group.updateMatrixWorld(true);
  const centre = new THREE.Vector3((x0 + x1) / 2, (y0 + y1) / 2, -d).applyMatrix4(cam.c2w);
  return { group, wire, quad, centre, top: top.clone().applyMatrix4(cam.c2w), depth: d };
}

// A frustum drawn as FRUSTA says for its kind; `rgb` for a kind coloured from a ramp (rounds).
const styled = (frame, style, order = 1, rgb = style.rgb) => frustum(frame, new THREE.Color(css(rgb)),
  { fill: style.fill, opacity: style.opacity, order });

// Round k of n on the rounds ramp: the first round at its start, the last at its end.
const roundColour = (k, n) => rampColour(FRUSTA.round.ramp, n > 1 ? k / (n - 1) : 0);

// The training cameras, or with a capture shown its rounds' cameras (the training cameras are
// the capture's photos less its test photos: drawn once, in their round's colour) and next poses.
function drawTraining() {
  if (view.trainingGroup) view.scene.remove(view.trainingGroup);
  view.trainingGroup = new THREE.Group();
  const rounds = view.capture ? view.capture.rounds : [];
  view.roundFrusta = rounds.map((r, k) => {
    const rgb = roundColour(k, rounds.length);
    return { round: r.round, rgb, frusta: r.captured.map((frame) => styled(frame, FRUSTA.round, 1, rgb)) };
  });
  view.nextFrusta = (rounds.length && rounds[rounds.length - 1].next || []).map((frame) => styled(frame, FRUSTA.next, 2));
  const frusta = view.capture ? view.roundFrusta.flatMap((r) => r.frusta).concat(view.nextFrusta) :
    view.training.map((frame) => styled(frame, FRUSTA.training));
  for (const f of frusta) view.trainingGroup.add(f.group);
  view.scene.add(view.trainingGroup);
}

// Drawn before the candidates (a lower order), so a candidate is never hidden under a target.
function drawTargets() {
  if (view.targetGroup) view.scene.remove(view.targetGroup);
  view.targetGroup = new THREE.Group();
  view.targetFrusta = view.targets.map((frame) => styled(frame, FRUSTA.target, 2));
  for (const f of view.targetFrusta) view.targetGroup.add(f.group);
  view.targetGroup.visible = view.targetsShown;
  view.scene.add(view.targetGroup);
  draw();
}

function drawCandidates() {
  if (view.candidateGroup) view.scene.remove(view.candidateGroup);
  view.candidateGroup = new THREE.Group();
  view.frusta = [];
  view.labels.replaceChildren();
  const r = view.ranking;
  if (!r) { draw(); return; }
  const scores = r.views.map((v) => v.score);
  const lo = Math.min(...scores), hi = Math.max(...scores);
  const returned = new Set(r.views.map((v) => v.index));
  (view.allCandidates || []).forEach((frame, index) => {
    if (!returned.has(index)) view.candidateGroup.add(styled(frame, FRUSTA.unreturned, 2).group);
  });
  // Low ranks drawn last: the first to capture lies on top where frusta overlap.
  [...r.views].sort((a, b) => b.rank - a.rank).forEach((v, k) => {
    const rgb = rampColour("score", hi > lo ? (v.score - lo) / (hi - lo) : 1);
    const f = frustum(v.camera, new THREE.Color(css(rgb)), { fill: 0.9, order: 3 + k });
    f.quad.userData.index = v.index;
    const label = el("span", { class: "v3d-label", text: "#" + v.rank, "data-index": v.index });
    view.labels.append(label);
    view.frusta.push(Object.assign(f, { index: v.index, rank: v.rank, score: v.score, rgb, label }));
    view.candidateGroup.add(f.group);
  });
  view.scene.add(view.candidateGroup);
  highlight();
}

function highlight() {
  for (const f of view.frusta) {
    const on = f.index === view.selected;
    f.wire.material.color.set(on ? 0xffffff : new THREE.Color(css(f.rgb)));
    f.label.classList.toggle("selected", on);
  }
  draw();
}

// Labels follow their frusta: the HTML overlay is placed where each frustum's up mark projects.
function placeLabels() {
  const width = view.stage.clientWidth, height = view.stage.clientHeight;
  for (const f of view.frusta) {
    const p = f.top.clone().project(view.camera);
    const visible = p.z < 1 && Math.abs(p.x) <= 1.05 && Math.abs(p.y) <= 1.05;
    f.label.hidden = !visible;
    f.label.style.left = ((p.x + 1) / 2 * width).toFixed(1) + "px";
    f.label.style.top = ((1 - p.y) / 2 * height).toFixed(1) + "px";
  }
}

// ------------------------------------------------------------------ drawing

let drawQueued = false;
function draw() {
  if (!view.renderer || drawQueued) return;
  drawQueued = true;
  requestAnimationFrame(() => {
    drawQueued = false;
    drawNow();
  });
}

function drawNow() {
  if (view.points) {
    const height = view.renderer.domElement.height;
    view.points.material.uniforms.projScale.value = height / (2 * Math.tan(THREE.MathUtils.degToRad(view.camera.fov) / 2));
  }
  sortPoints();
  view.renderer.render(view.scene, view.camera);
  placeLabels();
}

// Look at the scene's centre from 40 degrees above the mean training camera's side, from the
// nearest distance at which every camera drawn and the splats' box are in the picture.
function fit() {
  const up = new THREE.Vector3(...view.up).normalize();
  const frames = view.training.concat(view.ranking ? view.ranking.views.map((v) => v.camera) : [])
    .concat(view.allCandidates || [], view.targets, captureFrames());
  const b = view.header ? view.header.bounds : { min: [-1, -1, -1], max: [1, 1, 1] };
  const centre = new THREE.Vector3(...b.min).add(new THREE.Vector3(...b.max)).multiplyScalar(0.5);
  const shown = [0, 1, 2, 3, 4, 5, 6, 7].map((k) => new THREE.Vector3(k & 1 ? b.max[0] : b.min[0],
    k & 2 ? b.max[1] : b.min[1], k & 4 ? b.max[2] : b.min[2]));
  const mean = new THREE.Vector3();
  for (const frame of frames) {
    const p = new THREE.Vector3().setFromMatrixPosition(frameCamera(frame).c2w);
    shown.push(p);
    mean.add(p);
  }
  const reach = Math.max(...shown.map((p) => p.distanceTo(centre)), 1e-6);
  view.radius = reach;
  view.centre.copy(centre);
  let away = frames.length ? mean.multiplyScalar(1 / frames.length).sub(centre) : new THREE.Vector3(1, -1, 0);
  away.addScaledVector(up, -away.dot(up));                      // horizontal part
  if (away.lengthSq() < 1e-12) away = new THREE.Vector3(1, 0, 0).cross(up);
  if (away.lengthSq() < 1e-12) away = new THREE.Vector3(0, 1, 0).cross(up);
  const direction = away.normalize().multiplyScalar(Math.cos(0.7)).addScaledVector(up, Math.sin(0.7));   // 40 degrees
  view.camera.up.copy(up);
  view.camera.near = reach / 200;
  view.camera.far = reach * 20;
  view.controls.target.copy(centre);
  for (let distance = 0.8 * reach, k = 0; k < 40; k++, distance *= 1.08) {
    view.camera.position.copy(centre).addScaledVector(direction, distance);
    view.camera.lookAt(centre);
    view.camera.updateMatrixWorld();
    const fits = shown.every((p) => { const q = p.clone().project(view.camera); return q.z < 1 && Math.abs(q.x) < 0.9 && Math.abs(q.y) < 0.8; });
    if (fits) break;
  }
  view.camera.far = view.camera.position.distanceTo(centre) + 4 * reach;
  view.camera.updateProjectionMatrix();
  view.controls.update();
  view.sortPending = true;
  draw();
}

// ------------------------------------------------------------------ colouring by the explanation

function setMode(name) {
  if (!MODES[name]) throw new ViewError("unknown mode " + name);
  view.mode = name;
  for (const input of view.modes.querySelectorAll("input")) input.checked = input.value === name;
  if (name === "colour") { applyMode(); return Promise.resolve(); }
  return explainModel().then(applyMode).catch((err) => {
    say(err instanceof ViewError ? err.message : "error: " + err, true);
  });
}

function applyMode() {
  const points = view.points;
  if (!points) return;
  const uniforms = points.material.uniforms;
  const values = view.explained && view.explained.values[view.mode];
  if (view.mode === "colour" || !values || nothingNew()) {
    uniforms.mode.value = 0;                 // the splats' own colours; nothingNew says why in words
    if (nothingNew()) say(NOTHING_NEW);
  } else {
    say(measured(view.explained.result));   // what the explanation measured (not NOTHING_NEW from before)
    points.geometry.setAttribute("value", new THREE.BufferAttribute(values, 1, true));
    uniforms.mode.value = 1;
    uniforms.ramp.value = RAMPS[view.mode].map((c) => new THREE.Vector3(...c.map((v) => v / 255)));
  }
  drawLegend();
  draw();
}

// Whether "seen by #1" has nothing to show: the first pick sees no part of a splat the captured
// views had not (its explained novelty's scale is 0), which the status line then says in words.
const nothingNew = () => view.mode === "novelty" && view.explained && view.explained.result.scales.novelty === 0;

// What an explanation measured, in the status line.
const measured = (result) => `${result.num_views} training views, N = ${result.samples}, dropout ratio ` +
  `${result.dropout_ratio}: ${(100 * result.unseen_share).toFixed(1)} % of the splats no training view saw`;

function pickFrame() {
  const first = view.ranking && view.ranking.views.find((v) => v.rank === 1);
  return first ? first.camera : null;
}

// The explain job for this model (and the ranking's first pick): run once per pick, as a job.
async function explainModel() {
  if (!view.header) throw new ViewError("this model has no splats to colour");
  const pick = pickFrame();
  if (view.mode === "novelty" && !pick) throw new ViewError("rank first: the first pick is what 'seen by #1' shows");
  const key = view.modelId + ":" + JSON.stringify(pick);   // per model: a new model's explanation is its own
  if (view.explained && view.explained.key === key) return;
  if (view.explaining && view.explaining.key === key) return view.explaining.promise;
  const largest = Math.max(...view.training.map((f) => Math.max(f.w || 0, f.h || 0)), 1);
  const body = { samples: EXPLAIN_SAMPLES, downscale: Math.max(1, largest / EXPLAIN_SIDE), cap: view.header.cap, async: true };
  if (pick) body.pick = pick;
  const modelId = view.modelId;
  const mine = { key, promise: null };
  mine.promise = (async () => {
    say("measuring coverage and fragility on " + view.training.length + " training views...");
    view.progress.hidden = false;
    view.progress.value = 0;
    try {
      const first = await (await request(`/v1/models/${modelId}/explain`, { method: "POST", json: body })).json();
      let result = first;
      if (first.id && first.state) {
        for (let polls = 0; ; polls++) {
          const job = await (await request("/v1/jobs/" + first.id)).json();
          view.progress.value = job.progress;
          if (job.state === "succeeded") { result = job.result; break; }
          if (job.state === "failed") throw new ViewError(PLAIN[job.error.code] || job.error.message, job.error.code);
          if (job.state === "cancelled") throw new ViewError("the explanation was cancelled");
          await new Promise((resolve) => setTimeout(resolve, Math.min(250, 40 + 20 * polls)));
        }
      }
      if (modelId !== view.modelId) return;
      if (result.count !== view.header.count) throw new ViewError("the explanation is for other points than those drawn");
      const decode = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
      view.explained = { key, result, values: Object.fromEntries(Object.entries(result.values).map(([k, v]) => [k, decode(v)])) };
      say(measured(result));
    } finally {
      view.progress.hidden = true;
      if (view.explaining === mine) view.explaining = null;   // a newer request stays
    }
  })();
  view.explaining = mine;
  return mine.promise;
}

const SVG = "http://www.w3.org/2000/svg";

// A legend swatch: a small frustum (image rectangle, the edges to its centre, the up mark) on the
// view's background, drawn in the wire colour, opacity and fill FRUSTA gives that kind.
function glyph(kind, rgb = FRUSTA[kind].rgb) {
  const style = Object.assign({}, FRUSTA[kind], { rgb });
  const svg = document.createElementNS(SVG, "svg");
  const path = document.createElementNS(SVG, "path");
  for (const [k, v] of Object.entries({ class: `v3d-glyph ${kind}`, viewBox: "0 0 22 16", width: "22", height: "16" })) svg.setAttribute(k, v);
  for (const [k, v] of Object.entries({ d: "M4 5H18V14H4ZM4 5L11 9.5L18 5M4 14L11 9.5L18 14M8 5L11 2L14 5", stroke: css(style.rgb),
    "stroke-opacity": style.opacity, fill: style.fill ? css(style.rgb) : "none", "fill-opacity": style.fill })) path.setAttribute(k, v);
  svg.append(path);
  return svg;
}

const NOTHING_NEW = "#1 shows no part of a splat that the training views had not already shown, so no splat is " +
  "coloured here: its score comes from seeing splats from new angles and from where the model is unsure (fragility).";

function drawLegend() {
  const parts = [];
  if (view.ranking) {
    const bar = el("span", { class: "v3d-ramp score" });
    parts.push(el("span", { class: "v3d-key" }, el("span", { text: "candidate score: low " }), bar, el("span", { text: " high (capture first); #n = rank" })));
  }
  if (view.capture) {            // one key per round (its photos), and the poses to capture next
    view.roundFrusta.forEach((r) => parts.push(el("span", { class: "v3d-key v3d-round", "data-round": r.round },
      glyph("round", r.rgb), el("span", { text: ` round ${r.round} (${r.frusta.length})` }))));
    if (view.nextFrusta.length) {
      parts.push(el("span", { class: "v3d-key" }, glyph("next"), el("span", { text: ` capture next (${view.nextFrusta.length})` })));
    }
  } else {
    parts.push(el("span", { class: "v3d-key" }, glyph("training"), el("span", { text: " training camera" })));
  }
  if (view.targets.length) {     // a check box: the target views' frusta shown or hidden
    const box = el("input", { type: "checkbox", class: "v3d-targets-shown" });
    box.checked = view.targetsShown;
    box.addEventListener("change", () => showTargetFrusta(box.checked));
    parts.push(el("label", { class: "v3d-key" }, box, glyph("target"), el("span", { text: ` target view (${view.targets.length})` })));
  }
  if (view.ranking && view.allCandidates && view.allCandidates.length > view.ranking.views.length) {
    parts.push(el("span", { class: "v3d-key" }, glyph("unreturned"), el("span", { text: " not returned" })));
  }
  const mode = MODES[view.mode];
  if (mode.legend && view.explained && view.explained.values[view.mode] && !nothingNew()) {
    const scale = view.explained.result.scales[view.mode];
    const top = { coverage: `${scale}+ views`, fragility: `zeta ${Number(scale).toPrecision(3)}`,
      novelty: `${(100 * scale).toPrecision(2)} % of it or more` }[view.mode];
    parts.push(el("span", { class: "v3d-key" }, el("span", { text: `${mode.legend[0]} (0) ` }),
      el("span", { class: "v3d-ramp " + view.mode }), el("span", { text: ` ${mode.legend[1]} (${top})` })));
    if (view.mode !== "coverage") parts.push(el("span", { class: "v3d-key" }, el("span", { class: "v3d-swatch unseen" }), el("span", { text: " no view shows it" })));
  }
  view.legend.replaceChildren(...parts);
}

// ------------------------------------------------------------------ picking and selection

function clicked(event) {
  const rect = view.renderer.domElement.getBoundingClientRect();
  const ndc = new THREE.Vector2((event.clientX - rect.left) / rect.width * 2 - 1, -((event.clientY - rect.top) / rect.height) * 2 + 1);
  const ray = new THREE.Raycaster();
  ray.setFromCamera(ndc, view.camera);
  // The frustum drawn on top wins: the quads are drawn in rank order, the first rank last.
  const hits = ray.intersectObjects(view.frusta.map((f) => f.quad), false);
  if (!hits.length) return;
  const top = hits.reduce((best, h) => (h.object.renderOrder > best.object.renderOrder ? h : best));
  const index = top.object.userData.index;
  select(index);
  for (const callback of view.pickCallbacks) callback(index);
}

async function select(index) {
  if (view.noWebGL) return;
  const v = view.ranking && view.ranking.views.find((x) => x.index === index);
  view.selected = v ? index : null;
  highlight();
  view.blobs.forEach((u) => URL.revokeObjectURL(u));
  view.blobs = [];
  if (!v) { view.detail.hidden = true; return; }
  const images = [["render", v.render_url || (v.render_png && "data:image/png;base64," + v.render_png)],
    ["zeta", v.heatmap_url || (v.heatmap_png && "data:image/png;base64," + v.heatmap_png)]];
  const figures = images.filter(([, url]) => url).map(([caption, url]) => {
    const img = el("img", { alt: `${caption} of candidate ${index}`, class: caption === "zeta" ? "heatmap" : "render" });
    return { figure: el("figure", {}, img, el("figcaption", { text: caption })), img, url };
  });
  view.detail.replaceChildren(el("p", { class: "v3d-title", text: `#${v.rank}: candidate ${v.index}, score ${Number(v.score).toPrecision(4)}` }),
    el("div", { class: "v3d-pair" }, ...figures.map((f) => f.figure)));
  view.detail.hidden = false;
  await Promise.all(figures.map(async ({ img, url }) => {
    if (!url.startsWith("data:")) {
      url = URL.createObjectURL(await (await request(url)).blob());
      view.blobs.push(url);
    }
    await new Promise((resolve, reject) => { img.onload = resolve; img.onerror = () => reject(new ViewError("could not show " + url)); img.src = url; });
  }));
}

// ------------------------------------------------------------------ the API

async function mount(element, { modelId, headers = {} }) {
  if (!element) throw new ViewError("no element to draw in");
  if (view.noWebGL) return false;
  if (view.root !== element && !build(element)) return false;
  Object.assign(view, { headers, modelId, ranking: null, allCandidates: null, selected: null, explained: null, touched: false });
  if (view.points) { view.scene.remove(view.points); view.points.geometry.dispose(); view.points = null; }
  view.labels.replaceChildren();
  view.detail.hidden = true;
  view.frusta = [];
  if (view.candidateGroup) view.scene.remove(view.candidateGroup);
  if (!modelId) {                                  // nothing to load: a capture's cameras alone
    Object.assign(view, { header: null, training: [], up: meanUp(captureFrames()) });
    say(view.capture ? "no model trained on this capture yet: its cameras are shown" : "");
    fit();
    drawFrusta();
    return true;
  }
  say("loading the model...");
  const [scene, cameras] = await Promise.all([
    request(`/v1/models/${modelId}/scene`).then((r) => r.arrayBuffer()).then(parseScene).catch((err) => err),
    request(`/v1/models/${modelId}/cameras`).then((r) => r.json()),
  ]);
  if (modelId !== view.modelId) return false;      // another model was mounted meanwhile
  view.training = cameras.frames || [];
  view.up = cameras.up || [0, 0, 1];
  if (scene instanceof Error) {
    view.header = null;
    say("no splats to draw (" + scene.message + "); the cameras are shown", true);
  } else {
    view.header = scene.header;
    view.positions = scene.arrays.positions;
    view.points = makePoints(scene);
    view.scene.add(view.points);
    const h = scene.header;
    say(h.count < h.total ? `${h.count.toLocaleString("en")} of ${h.total.toLocaleString("en")} splats drawn (cap ${h.cap.toLocaleString("en")}, ` +
      "drawn by opacity and size)" : `${h.total.toLocaleString("en")} splats`);
  }
  fit();
  drawFrusta();
  if (view.mode !== "colour") await setMode(view.mode);
  return true;
}

function showRanking(result, { candidates = null } = {}) {
  if (view.noWebGL) return;
  if (!view.renderer) throw new ViewError("mount the view on a model first");
  view.ranking = result;
  view.allCandidates = candidates;
  view.selected = null;
  view.detail.hidden = true;
  if (view.mode !== "colour") setMode(view.mode);        // a new first pick: explained again (novelty)
  if (!view.touched) fit();
  drawFrusta();
}

// The target views: fitted into the picture unless the user has turned the view.
function showTargets(frames) {
  view.targets = frames;
  if (view.noWebGL || !view.renderer) return;   // drawn when a model is mounted
  if (!view.touched) fit();
  drawFrusta();
}

// A capture's rounds in place of the training cameras (null: the training cameras again). The
// view is built on them when no model was mounted yet: a capture has cameras before it has a model.
function showCapture(element, capture) {
  if (view.noWebGL) return false;
  if (!view.renderer && !capture) return true;          // nothing drawn yet, nothing to take away
  if (!view.renderer && !build(element)) return false;
  view.capture = capture && { rounds: capture.rounds };
  if (!view.touched) fit();
  drawFrusta();
  return true;
}

// Without a model the service has worked out no up (GET /cameras): the cameras' mean up axis (their
// image's +y, OpenGL), +z when they cancel out.
function meanUp(frames) {
  const sum = new THREE.Vector3();
  for (const frame of frames) sum.add(new THREE.Vector3().setFromMatrixColumn(frameCamera(frame).c2w, 1));
  return sum.lengthSq() > 1e-12 ? sum.normalize().toArray() : [0, 0, 1];
}

const captureFrames = () => (view.capture ? view.capture.rounds.flatMap((r) => r.captured.concat(r.next || [])) : []);

// The legend's check box: the target views' frusta shown or not (they stay in the legend either way).
function showTargetFrusta(shown) {
  view.targetsShown = shown;
  if (view.targetGroup) view.targetGroup.visible = shown;
  draw();
}

// Every frustum again (their size follows the scene's reach, which fit() sets) and the legend.
function drawFrusta() {
  drawTraining();
  drawTargets();
  drawCandidates();
  drawLegend();
}

// No ranking (the candidates changed, or a new ranking runs): no frusta, no detail panel.
function clear() {
  if (!view.renderer) return;
  view.ranking = null;
  view.allCandidates = null;
  view.selected = null;
  view.detail.hidden = true;
  drawCandidates();
  drawLegend();
}

// The model changed on the server (calibrated): explain it again for the mode shown.
function refresh() {
  if (!view.renderer) return Promise.resolve();
  view.explained = null;
  view.explaining = null;
  if (view.status.classList.contains("error")) say("");    // an old "calibrate first" is no longer true
  return setMode(view.mode);
}

function onPick(callback) {
  view.pickCallbacks.push(callback);
}

function debug() {
  view.camera.updateMatrixWorld();
  return {
    width: view.stage.clientWidth, height: view.stage.clientHeight,
    projection: view.camera.projectionMatrix.elements.slice(), view: view.camera.matrixWorldInverse.elements.slice(),
    frustumDepth: FRUSTUM_SHARE * view.radius, points: view.header ? view.header.count : 0,
    total: view.header ? view.header.total : 0, training: view.training.length, mode: view.mode,
    explained: view.explained ? Object.keys(view.explained.values) : [], selected: view.selected,
    frusta: view.frusta.map((f) => ({ index: f.index, rank: f.rank, rgb: f.rgb, centre: f.centre.toArray() })),
    targets: view.targetFrusta.map((f) => ({ rgb: FRUSTA.target.rgb, fill: FRUSTA.target.fill, centre: f.centre.toArray() })),
    targetsShown: view.targetsShown, styles: FRUSTA,
    rounds: view.roundFrusta.map((r) => ({ round: r.round, rgb: r.rgb, frusta: r.frusta.length })),
    next: view.nextFrusta.length,
    centre: view.centre.toArray(), up: view.up.slice(), sortMs: view.sortMs,
  };
}

// The style sheet travels with the script (one tag in the page): a same-origin file, as the CSP asks.
document.head.append(el("link", { rel: "stylesheet", href: new URL("view3d.css", import.meta.url).pathname }));
// drawNow: draw at once (tests read the canvas after it); with resort, sort the points again first.
window.phdView3d = { mount, showRanking, showTargets, showCapture, clear, refresh, onPick, select, setMode, debug,
  drawNow: (resort = false) => { view.sortPending = view.sortPending || resort; drawNow(); } };
