// The PH-Dropout page: a client of the REST API like any other (docs/service.md).
// Plain JavaScript, no framework, no inline code: the CSP allows script-src 'self' only.
// Images are fetched with the API key and shown through blob: URLs.
"use strict";

const state = {
  key: localStorage.getItem("phd-api-key") || "",
  models: [],
  training: [],        // frames of the chosen model's training cameras
  candidates: [],      // the user's own frames (file mode), sent as the rank request's cameras
  spec: null,          // generate mode: the rank request's candidates {generator, count, options}
  ranking: null,       // the last RankResult
  job: null,           // id of the running rank job (for Cancel)
  blobs: [],           // object URLs to revoke when a grid is redrawn
};

const $ = (id) => document.getElementById(id);

// ------------------------------------------------------------------ the API

class ApiError extends Error {}

async function api(path, options = {}) {
  const headers = Object.assign({}, options.headers || {});
  if (state.key) headers.Authorization = "Bearer " + state.key;
  let body = options.body;
  if (options.json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(options.json);
  }
  const response = await fetch(path, { method: options.method || "GET", headers, body });
  if (!response.ok) {
    let text = response.status + " " + response.statusText;
    try {
      const e = (await response.json()).error;
      text = e.code + ": " + e.message + (e.field ? " (field " + e.field + ")" : "");
    } catch (_) { /* not our error shape */ }
    throw new ApiError(text);
  }
  return response;
}

async function apiJson(path, options) {
  const response = await api(path, options);
  return response.status === 204 ? null : { status: response.status, data: await response.json() };
}

// POST a work request as a job and poll it, showing progress; resolves to the job's result.
async function runJob(path, body, bar, onJob) {
  bar.hidden = false;
  bar.value = 0;
  const first = await apiJson(path, { method: "POST", json: Object.assign({}, body, { async: true }) });
  if (first.status !== 202) { bar.value = 1; return first.data; }   // answered at once
  const id = first.data.id;
  if (onJob) onJob(id);
  for (let polls = 0; ; polls++) {
    const job = (await apiJson("/v1/jobs/" + id)).data;
    bar.value = job.progress;
    if (job.state === "succeeded") return job.result;
    if (job.state === "failed") throw new ApiError(job.error.code + ": " + job.error.message);
    if (job.state === "cancelled") throw new ApiError("the job was cancelled");
    // Short jobs answer fast; long ones are polled four times a second.
    await new Promise((resolve) => setTimeout(resolve, Math.min(250, 40 + 20 * polls)));
  }
}

// An image the API serves (needs the key): fetched, then shown from a blob: URL.
async function loadImage(img, url) {
  const blob = await (await api(url)).blob();
  const objectUrl = URL.createObjectURL(blob);
  state.blobs.push(objectUrl);
  await new Promise((resolve, reject) => {
    img.onload = resolve;
    img.onerror = () => reject(new ApiError("could not decode " + url));
    img.src = objectUrl;
  });
}

function say(text, isError = false) {
  const p = $("message");
  p.textContent = text;
  p.classList.toggle("error", isError);
}

async function guarded(action) {
  say("");                             // an old error does not outlive the next action
  try {
    await action();
  } catch (err) {
    say(err instanceof ApiError ? err.message : "error: " + err, true);
  }
}

// ------------------------------------------------------------------ small helpers

const fmt = (x, digits = 4) => (x === null || x === undefined ? "-" : Number(x).toPrecision(digits));

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v; else if (k === "text") node.textContent = v; else node.setAttribute(k, v);
  }
  for (const child of children) node.append(child);
  return node;
}

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.sqrt(dot(a, a));
const unit = (a) => mul(a, 1 / (norm(a) || 1));

const position = (frame) => [0, 1, 2].map((i) => frame.transform_matrix[i][3]);
const column = (frame, j) => [0, 1, 2].map((i) => frame.transform_matrix[i][j]);

// ------------------------------------------------------------------ models

async function loadModels(selectId) {
  state.models = (await apiJson("/v1/models")).data.models;
  for (const [id, keep] of [["model-select", selectId], ["model-b-select", $("model-b-select").value]]) {
    const select = $(id);
    select.replaceChildren(...state.models.map((m) => el("option", { value: m.id, text: m.name + " (" + m.kind + ", " + m.num_units + " units)" })));
    if (keep && state.models.some((m) => m.id === keep)) select.value = keep;
  }
  if (state.models.length > 1 && $("model-b-select").value === $("model-select").value) {
    $("model-b-select").value = state.models.find((m) => m.id !== $("model-select").value).id;
  }
  await modelChosen();
}

function currentModel() {
  return state.models.find((m) => m.id === $("model-select").value) || null;
}

async function modelChosen() {
  const model = currentModel();
  state.training = [];
  if (!model) {
    $("model-info").textContent = "No model yet: upload one below.";
  } else {
    const cal = model.calibration;
    $("model-info").textContent = model.kind + ", " + model.num_units + " dropout units, " +
      model.num_training_cameras + " training cameras, " +
      (cal ? "calibrated: r_drop = " + cal.r_drop : "not calibrated (calibrate it, or ranking answers 409)");
    if (model.has_training_cameras) state.training = (await apiJson("/v1/models/" + model.id + "/cameras")).data.frames;
  }
  await updateCandidates();
}

async function upload(event) {
  event.preventDefault();
  const form = new FormData();
  form.append("file", $("upload-file").files[0]);
  if ($("upload-cameras").files[0]) form.append("cameras", await $("upload-cameras").files[0].text());
  if ($("upload-name").value) form.append("name", $("upload-name").value);
  say("uploading...");
  const info = (await apiJson("/v1/models", { method: "POST", body: form })).data;
  say("uploaded " + info.name);
  await loadModels(info.id);
}

async function calibrate() {
  const model = currentModel();
  if (!model) throw new ApiError("choose or upload a model first");
  say("calibrating " + model.name + "...");
  const result = await runJob("/v1/models/" + model.id + "/calibrate",
    { samples: Number($("cal-samples").value), downscale: Number($("cal-downscale").value) }, $("cal-progress"));
  say("calibrated: r_drop = " + result.r_drop);
  await loadModels(model.id);
}

async function deleteModel() {
  const model = currentModel();
  if (!model || !window.confirm("Delete " + model.name + "?")) return;
  await api("/v1/models/" + model.id, { method: "DELETE" });
  say("deleted " + model.name);
  await loadModels();
}

// ------------------------------------------------------------------ candidates

// The plots' frame: where the training cameras look (the point nearest to all their optical
// axes, least squares), their mean up vector and their median distance to that point.
function captureFrame() {
  const frames = state.training;
  const model = currentModel();
  if (frames.length === 0) {
    const b = model && model.bounds;
    const center = b ? mul(add(b.min, b.max), 0.5) : [0, 0, 0];
    const radius = b ? Math.max(norm(sub(b.max, b.min)), 1e-3) * 1.5 : 4;
    return { center, up: [0, 0, 1], radius };
  }
  const A = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  let rhs = [0, 0, 0];
  let up = [0, 0, 0];
  for (const f of frames) {
    const p = position(f);
    const d = unit(mul(column(f, 2), -1));  // OpenGL: the camera looks along -z
    for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) A[i][j] += (i === j ? 1 : 0) - d[i] * d[j];
    rhs = add(rhs, sub(p, mul(d, dot(d, p))));
    up = add(up, column(f, 1));
  }
  let center = solve3(A, rhs);
  if (!center) center = mul(frames.map(position).reduce(add, [0, 0, 0]), 1 / frames.length);
  const distances = frames.map((f) => norm(sub(position(f), center))).sort((a, b) => a - b);
  return { center, up: unit(up), radius: distances[Math.floor(distances.length / 2)] };
}

function solve3(A, b) {  // Cramer's rule; null when (nearly) singular, e.g. parallel axes
  const det = (m) => m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
    m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
  const d = det(A);
  if (Math.abs(d) < 1e-6) return null;
  return [0, 1, 2].map((k) => det(A.map((row, i) => row.map((v, j) => (j === k ? b[i] : v)))) / d);
}

function horizontalAxes(up) {
  const helper = Math.abs(up[0]) > 0.9 ? [0, 1, 0] : [1, 0, 0];
  const ax = unit(cross(up, helper));
  return [ax, cross(up, ax)];
}

// The service makes generated poses (its candidate generators); the page only draws them.
function candidateSpec() {
  const count = Math.max(1, Math.min(1000, Number($("gen-count").value) || 1));
  const ring = $("gen-shape").value === "ring";
  const options = ring ? { elevation: (Number($("gen-elevation").value) || 0) * Math.PI / 180 } : {};
  const factor = Number($("gen-radius").value) || 1;
  if (factor !== 1 && state.training.length) options.radius = captureFrame().radius * factor;
  return { generator: ring ? "orbit" : "hemisphere", count, options };
}

// The poses to draw and to select over: the user's own list, or those the last ranking returned.
function shownCandidates() {
  if (state.spec === null) return state.candidates.map((frame, index) => ({ index, frame }));
  return state.ranking ? state.ranking.views.map((v) => ({ index: v.index, frame: v.camera })) : [];
}

async function updateCandidates() {
  const mode = document.querySelector("input[name=cand-mode]:checked").value;
  $("generate-options").hidden = mode !== "generate";
  $("file-options").hidden = mode !== "file";
  state.candidates = [];
  state.spec = null;
  if (mode === "generate") {
    state.spec = candidateSpec();
    $("cand-info").textContent = state.spec.count + " " + state.spec.generator + " poses, made by the service " +
      (state.training.length ? "around the training cameras" : "around the model's splats") +
      " when you rank; the plots show the poses it returns";
  } else {
    const file = $("cand-file").files[0];
    if (file) {
      const data = JSON.parse(await file.text());
      const frames = Array.isArray(data) ? data : data.frames || [];
      const defaults = Array.isArray(data) ? {} : data;
      state.candidates = frames.map((f) => Object.assign({}, Object.fromEntries(Object.entries(defaults).filter(([k]) => k !== "frames")), f));
      $("cand-info").textContent = state.candidates.length + " poses from " + file.name;
    } else {
      $("cand-info").textContent = "choose a JSON file of candidate poses";
    }
  }
  state.ranking = null;               // a ranking belongs to the candidates it ranked
  $("rank-grid").replaceChildren();
  $("rank-summary").textContent = "";
  drawPlots();
}

// ------------------------------------------------------------------ plots (inline SVG)

const SVG = "http://www.w3.org/2000/svg";

function svgEl(tag, attrs) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  return node;
}

// Score in [0, 1] -> a colour from dark blue (low) through teal and green to yellow (high).
const RAMP = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
function scoreColour(t) {
  const x = Math.max(0, Math.min(1, t)) * (RAMP.length - 1);
  const i = Math.min(RAMP.length - 2, Math.floor(x));
  const c = RAMP[i].map((v, k) => Math.round(v + (RAMP[i + 1][k] - v) * (x - i)));
  return "rgb(" + c.join(",") + ")";
}

function drawPlots() {
  const frame = captureFrame();
  const [ax, ay] = horizontalAxes(frame.up);
  const views = [[ax, ay], [ax, frame.up]];   // from above, from the side
  const scored = new Map();
  if (state.ranking) for (const v of state.ranking.views) scored.set(v.index, v);
  const scores = [...scored.values()].map((v) => v.score);
  const lo = Math.min(...scores), hi = Math.max(...scores);
  ["plot-top", "plot-side"].forEach((id, k) => {
    const [u, w] = views[k];
    const project = (frame_) => { const p = sub(position(frame_), frame.center); return [dot(p, u), dot(p, w)]; };
    const shown = shownCandidates();
    const points = state.training.map(project).concat(shown.map((c) => project(c.frame)));
    const extent = Math.max(1e-6, ...points.map((p) => Math.max(Math.abs(p[0]), Math.abs(p[1])))) * 1.1;
    const xy = (p) => [150 + 140 * p[0] / extent, 150 - 140 * p[1] / extent];
    const svg = $(id);
    svg.replaceChildren(svgEl("circle", { cx: 150, cy: 150, r: 3, class: "centre" }));
    for (const f of state.training) {
      const [x, y] = xy(project(f));
      const mark = svgEl("path", { d: `M${x - 4},${y - 4}L${x + 4},${y + 4}M${x - 4},${y + 4}L${x + 4},${y - 4}`, class: "train" });
      mark.append(svgEl("title", {}));
      mark.firstChild.textContent = "training camera";
      svg.append(mark);
    }
    // Unscored first, then scored from low to high, so the most uncertain are drawn on top.
    const order = [...shown].sort((a, b) => (scored.get(a.index)?.score ?? -Infinity) - (scored.get(b.index)?.score ?? -Infinity));
    for (const { index: i, frame: pose } of order) {
      const [x, y] = xy(project(pose));
      const view = scored.get(i);
      const dotEl = svgEl("circle", { cx: x, cy: y, r: view ? 6 : 4, class: view ? "cand" : "cand none", "data-index": i });
      if (view) dotEl.setAttribute("fill", scoreColour(hi > lo ? (view.score - lo) / (hi - lo) : 1));
      const title = svgEl("title", {});
      title.textContent = view ? `candidate ${i}: rank ${view.rank}, score ${fmt(view.score)}` : `candidate ${i}`;
      dotEl.append(title);
      dotEl.addEventListener("click", () => focusCard(i));
      svg.append(dotEl);
      if (view && view.rank < 3) {
        const label = svgEl("text", { x: x + 7, y: y - 7, class: "label" });
        label.textContent = String(view.rank + 1);
        svg.append(label);
      }
    }
  });
}

function focusCard(index) {
  const card = document.querySelector(`#rank-grid li[data-index="${index}"]`);
  if (!card) return;
  document.querySelectorAll("#rank-grid li.focus").forEach((c) => c.classList.remove("focus"));
  card.classList.add("focus");
  card.scrollIntoView({ block: "nearest" });
}

// ------------------------------------------------------------------ rank

function sizeOptions(prefix) {
  const downscale = Number($(prefix + "-downscale").value);
  return downscale > 0 ? { downscale } : {};
}

async function rank(event) {
  event.preventDefault();
  const model = currentModel();
  if (!model) throw new ApiError("choose or upload a model first");
  if (state.spec === null && state.candidates.length === 0) throw new ApiError("no candidate poses: choose a file");
  const body = Object.assign({ samples: Number($("rank-samples").value), seed: Number($("rank-seed").value),
    heatmaps: "files" }, sizeOptions("rank"));
  if (state.spec !== null) body.candidates = state.spec; else body.cameras = state.candidates;
  if ($("rank-strategy").value) body.strategy = $("rank-strategy").value;
  if ($("rank-topk").value) body.top_k = Number($("rank-topk").value);
  say("ranking " + (state.spec ? state.spec.count : state.candidates.length) + " candidates...");
  state.ranking = null;
  $("rank-grid").replaceChildren();      // no stale cards while the new ranking runs
  $("rank-summary").textContent = "";
  $("rank-run").disabled = true;
  $("rank-cancel").hidden = false;
  try {
    state.ranking = await runJob("/v1/models/" + model.id + "/rank", body, $("rank-progress"), (id) => { state.job = id; });
  } finally {
    state.job = null;
    $("rank-run").disabled = false;
    $("rank-cancel").hidden = true;
  }
  const r = state.ranking;
  $("rank-summary").textContent = `${r.views.length} of ${r.num_candidates} candidates, capture first comes first; ` +
    `strategy ${r.strategy}, dropout ratio ${r.dropout_ratio} (${r.ratio_source}), N = ${r.samples}, ${r.width}x${r.height} px; ` +
    `heat maps share one scale: yellow = zeta ${fmt(r.heatmap_vmax)}, dark blue = 0`;
  drawPlots();
  await drawRankGrid(r);
  say("ranked: capture candidate " + r.views[0].index + " first");
}

async function drawRankGrid(result) {
  state.blobs.forEach((u) => URL.revokeObjectURL(u));
  state.blobs = [];
  const grid = $("rank-grid");
  const loads = [];
  grid.replaceChildren(...result.views.map((v) => {
    const render = el("img", { class: "render", alt: "render of candidate " + v.index });
    const heat = el("img", { class: "heatmap", alt: "zeta heat map of candidate " + v.index });
    if (v.render_url) loads.push(loadImage(render, v.render_url));
    if (v.heatmap_url) loads.push(loadImage(heat, v.heatmap_url));
    return el("li", { class: "card", "data-index": v.index, "data-rank": v.rank },
      el("div", { class: "pair" },
        el("figure", {}, render, el("figcaption", { text: "render" })),
        el("figure", {}, heat, el("figcaption", { text: "zeta" }))),
      el("p", { class: "title", text: `#${v.rank + 1}  candidate ${v.index}` }),
      el("dl", {},
        el("dt", { text: "score" }), el("dd", { class: "score", text: fmt(v.score) }),
        el("dt", { text: "sigma_max" }), el("dd", { text: fmt(v.sigma_max) }),
        el("dt", { text: "sigma_mean" }), el("dd", { text: fmt(v.sigma_mean) })));
  }));
  grid.querySelectorAll("li").forEach((li) => li.addEventListener("click", () => {
    focusCard(li.dataset.index);
    document.querySelectorAll(".plot circle.picked").forEach((c) => c.classList.remove("picked"));
    document.querySelectorAll(`.plot circle[data-index="${li.dataset.index}"]`).forEach((c) => c.classList.add("picked"));
  }));
  await Promise.all(loads);
}

async function cancelRank() {
  if (state.job) await api("/v1/jobs/" + state.job, { method: "DELETE" });
}

// ------------------------------------------------------------------ select

async function select(event) {
  event.preventDefault();
  const a = currentModel(), bId = $("model-b-select").value;
  if (!a || !bId) throw new ApiError("choose two models");
  if (a.id === bId) throw new ApiError("model B must differ from model A");
  // Generated poses exist once the service made them: select over the ranked views' poses.
  const cameras = shownCandidates().map((c) => c.frame);
  if (cameras.length === 0) {
    throw new ApiError(state.spec ? "rank first: the service makes the generated poses" : "no candidate poses: choose a file");
  }
  say("selecting over " + cameras.length + " views...");
  $("select-grid").replaceChildren();
  $("select-summary").textContent = "";
  const body = Object.assign({ model_a: a.id, model_b: bId, cameras, rule: $("select-rule").value || undefined,
    samples: Number($("rank-samples").value), seed: Number($("rank-seed").value), images: "files", both_images: true },
  sizeOptions("rank"));
  const result = await runJob("/v1/select", body, $("select-progress"));
  const names = { a: a.name, b: (state.models.find((m) => m.id === bId) || { name: "B" }).name };
  $("select-summary").textContent = `A (${names.a}) trusted for ${result.counts.a} views, B (${names.b}) for ${result.counts.b}; ` +
    `rule ${result.rule} (lower score is trusted)`;
  const loads = [];
  $("select-grid").replaceChildren(...result.views.map((v) => {
    const urls = v.choice === "a" ? { a: v.image_url, b: v.other_image_url } : { a: v.other_image_url, b: v.image_url };
    const figures = ["a", "b"].map((key) => {
      const img = el("img", { class: "render", alt: `model ${key.toUpperCase()} render of view ${v.index}` });
      if (urls[key]) loads.push(loadImage(img, urls[key]));
      return el("figure", { class: v.choice === key ? "chosen" : "" }, img,
        el("figcaption", { text: `${key.toUpperCase()}: ${fmt(v["score_" + key], 3)}${v.choice === key ? " (trusted)" : ""}` }));
    });
    return el("li", { class: "card", "data-index": v.index, "data-choice": v.choice },
      el("div", { class: "pair" }, ...figures), el("p", { class: "title", text: `view ${v.index}: trust ${v.choice.toUpperCase()}` }));
  }));
  await Promise.all(loads);
  say("selection done");
}

// ------------------------------------------------------------------ start

async function readChoices() {
  try {
    const schemas = (await (await fetch("/openapi.json")).json()).components.schemas;
    const strategy = schemas.RankRequest.properties.strategy;
    $("rank-strategy").value = strategy.default || "";
    $("rank-strategy").title = strategy.description || "";
    $("strategies").replaceChildren(...(strategy.examples || []).map((n) => el("option", { value: n })));
    const rule = schemas.SelectRequest.properties.rule;
    $("select-rule").replaceChildren(...(rule.enum || []).map((n) =>
      el("option", { value: n, text: n === rule.default ? `${n} (default)` : n })));
    $("select-rule").value = rule.default || "";
    $("select-rule").title = rule.description || "";
  } catch (_) { /* the strategy stays free text, the rule list empty: the server's defaults apply */ }
}

function start() {
  $("api-key").value = state.key;
  $("key-form").addEventListener("submit", (e) => {
    e.preventDefault();
    state.key = $("api-key").value.trim();
    localStorage.setItem("phd-api-key", state.key);
    guarded(() => loadModels($("model-select").value).then(() => say("key saved in this browser")));
  });
  $("refresh-models").addEventListener("click", () => guarded(() => loadModels($("model-select").value)));
  $("model-select").addEventListener("change", () => guarded(modelChosen));
  $("delete-model").addEventListener("click", () => guarded(deleteModel));
  $("calibrate").addEventListener("click", () => guarded(calibrate));
  $("upload-form").addEventListener("submit", (e) => guarded(() => upload(e)));
  document.querySelectorAll("input[name=cand-mode], #generate-options input, #generate-options select, #cand-file")
    .forEach((input) => input.addEventListener("change", () => guarded(updateCandidates)));
  $("rank-form").addEventListener("submit", (e) => guarded(() => rank(e)));
  $("rank-cancel").addEventListener("click", () => guarded(cancelRank));
  $("select-form").addEventListener("submit", (e) => guarded(() => select(e)));
  readChoices();
  guarded(() => loadModels());
}

document.addEventListener("DOMContentLoaded", start);
