// The PH-Dropout page: a client of the REST API like any other (docs/service.md).
// Plain JavaScript, no framework, no inline code: the CSP allows script-src 'self' only.
// Images are fetched with the API key and shown through blob: URLs. Every action reports in
// the message line of its own section (errors scrolled into view), in words for people: the
// service's error codes and fields are turned into sentences here (PLAIN, LABELS).
"use strict";

const state = {
  key: localStorage.getItem("phd-api-key") || "",
  models: [],
  modelId: null,       // the model the page last set itself up for (downscale, 3D view)
  viewReady: false,    // the 3D view has drawn that model
  training: [],        // frames of the chosen model's training cameras
  up: [0, 0, 1],       // their capture's up, as the service works it out (GET /cameras)
  candidates: [],      // the user's own frames (file mode), sent as the rank request's cameras
  candidatesSized: true, // false: the file's frames lack w/h, taken from the width/height fields
  spec: null,          // generate mode: the rank request's candidates {generator, count, options}
  targets: [],         // frames of the target views file (where the model will be looked at from), [] for none
  ranking: null,       // the last RankResult, with the id of the model it ranked (modelId)
  rankToken: 0,        // raised when a rank starts or the candidates or targets change: an older job's answer is not drawn
  job: null,           // id of the running rank job (for Cancel)
  blobs: [],           // object URLs to revoke when a grid is redrawn
  dropped: null,       // files dropped on the upload zone: [{file, path}]
  uploadCameras: null, // the parsed training-cameras file of the upload form
  formats: [],         // the service's pose conventions (download)
};

const $ = (id) => document.getElementById(id);
const view3d = () => window.phdView3d || null;    // the 3D view (view3d.js), when the page has it

// ------------------------------------------------------------------ errors in plain words

// An error from the service (code, field) or from the page's own checks (code "page").
class ApiError extends Error {
  constructor(message, code = "page", field = null) {
    super(message);
    this.code = code;
    this.field = field;
  }
}

// The service's error codes, as a person at this page would be told (the message follows
// where it carries the particulars).
const PLAIN = {
  unauthorized: () => (state.key ? "The server refused this API key: check it and press \"Use key\" again." :
    "The server asks for an API key: type it at the top and press \"Use key\"."),
  no_training_cameras: () => "This model has no training cameras. " + NO_CAMERAS_ADVICE,
  not_calibrated: (m, field) => (field === "ratio_b" ? (modelB() && !calibratable(modelB()) ?
    "Model B has no training cameras, so it cannot be calibrated: upload it again with them, or choose another model B." :
    "Model B is not calibrated yet: press \"Calibrate model B\" beside Select.") :
    "This model is not calibrated yet: press \"Calibrate\" in section 1 first."),
  signal_mismatch: (m) => "The model was calibrated for another signal: calibrate it again. (" + m + ")",
  queue_full: () => "The server is busy with other work: try again in a few seconds.",
  busy: () => "The server's memory is taken by other work: try again in a few seconds.",
  payload_too_large: (m) => "Too large for this server: " + plainText(m),
  over_memory_budget: (m) => "Too large for this server's memory: raise \"downscale\" or lower \"samples\". (" +
    plainText(m) + ")",
  unsupported_model: (m) => "That file is not a model this service reads: " + plainText(m),
  unsupported_media_type: () => "The upload was not sent as a form: reload the page and try again.",
  model_not_found: () => "That model is no longer on the server: press \"Refresh\".",
  job_not_found: () => "The server no longer has that job: run it again.",
  job_cancelled: () => "Cancelled.",
  upload_incomplete: () => "The upload broke off before it was complete: try again.",
  request_timeout: () => "The connection was too slow and the server gave up: try again.",
  calibration_failed: (m) => "Calibration failed: " + plainText(m),
  cameras_of_another_capture: (m) => "The training cameras do not see this model: " + plainText(m) +
    " (tick the box above the Upload button only if they are right).",
  executor_failed: () => "The server's compute workers failed: try again, or tell whoever runs the server.",
  internal_error: () => "The server failed unexpectedly: tell whoever runs it (its log has the details).",
};

// Request fields -> what this page calls them (in the upload section, "cameras" are the training cameras).
const UPLOAD_LABELS = { cameras: "the training cameras" };
const LABELS = {
  samples: "samples", downscale: "downscale", width: "width", height: "height", top_k: "top k", seed: "seed",
  strategy: "strategy", cameras: "the candidate poses", candidates: "the generated candidates",
  "candidates.count": "count", "candidates.options.radius": "radius", "candidates.options.elevation": "elevation",
  training_cameras: "the training cameras", model_b: "model B", model_a: "model A", rule: "rule",
  file: "the model file", files: "the folder", archive: "the zip", name: "name", background: "background",
  camera_format: "the cameras' format", Authorization: "API key", format: "pose format", indices: "the poses",
  targets: "the target views",
};

// Request fields whose errors are shown beside their own control (the message line under it)
// rather than in the section's line.
const FIELD_LINES = { targets: "targets-message" };

// A service message without its API words: no routes, no "(field x)", no pydantic prefixes.
function plainText(message) {
  return String(message)
    .replace(/\s*\((?:POST|GET|DELETE) \/v1\/[^)]*\)/g, "")
    .replace(/\s*\(field '?[^)']*'?\)/g, "")
    .replace(/Value error, /g, "")
    .replace(/\bgive dropout_ratio\b/, "give a dropout ratio")
    .replace(/\bmodel '[0-9a-f]{16}'/g, "the model");
}

// A request field without its item and key: "targets[2].w" -> "targets".
const fieldBase = (field) => field.replace(/\[\d+\].*$/, "").replace(/\..*$/, "");

function fieldLabel(field, where) {
  if (!field) return null;
  const labels = where === "upload-message" ? Object.assign({}, LABELS, UPLOAD_LABELS) : LABELS;
  if (labels[field]) return labels[field];
  const base = fieldBase(field);
  const item = field.match(/\[(\d+)\]/);
  return (labels[base] || base.replace(/_/g, " ")) + (item ? " (pose " + item[1] + ")" : "");
}

function plain(err, where) {
  if (!(err instanceof ApiError)) return "Something went wrong in the page: " + err;
  if (err.code === "page") return err.message;
  if (PLAIN[err.code]) return PLAIN[err.code](err.message, err.field);
  const label = fieldLabel(err.field, where);
  let text = plainText(err.message);
  if (err.field) text = text.replace(new RegExp("^" + err.field.replace(/[.[\]]/g, "\\$&") + ":\\s*"), "");
  return (label ? label.charAt(0).toUpperCase() + label.slice(1) + ": " : "") + text;
}

const NO_CAMERAS_ADVICE = "Without them it cannot be calibrated, and candidates are placed around its splats. " +
  "Add them: upload the PLY again together with the .json sidecar phd train wrote beside it, or give its " +
  "transforms_train.json or cameras.json as \"Training cameras\", or upload the trainer's whole output folder.";

// ------------------------------------------------------------------ the API

async function api(path, options = {}) {
  const headers = Object.assign({}, options.headers || {});
  if (state.key) headers.Authorization = "Bearer " + state.key;
  let body = options.body;
  if (options.json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(options.json);
  }
  let response;
  try {
    response = await fetch(path, { method: options.method || "GET", headers, body });
  } catch (_) {
    throw new ApiError("The server cannot be reached: is it still running?");
  }
  if (!response.ok) {
    let error = null;
    try { error = (await response.json()).error; } catch (_) { /* not our error shape */ }
    if (error && error.code) throw new ApiError(error.message, error.code, error.field);
    throw new ApiError("The server answered with an error (" + response.status + " " + response.statusText + ").");
  }
  return response;
}

async function apiJson(path, options) {
  const response = await api(path, options);
  return response.status === 204 ? null : { status: response.status, data: await response.json() };
}

// POST a work request as a job and poll it, showing progress; resolves to the job's result.
// The bar is hidden again when the job ends, however it ends.
async function runJob(path, body, bar, onJob) {
  bar.hidden = false;
  bar.value = 0;
  try {
    const first = await apiJson(path, { method: "POST", json: Object.assign({}, body, { async: true }) });
    if (first.status !== 202) return first.data;   // answered at once
    if (onJob) onJob(first.data.id);
    return await pollJob(first.data.id, bar);
  } finally {
    bar.hidden = true;
  }
}

// A job's time left as the service estimates it (training), "" when it gives none.
function timeLeft(job) {
  if (job.eta_seconds == null) return "";
  const text = "about " + Math.ceil(job.eta_seconds) + " s left";
  return job.eta_max_seconds > 1.1 * job.eta_seconds + 1 ? text + " (at most " + Math.ceil(job.eta_max_seconds) + " s)" : text;
}

// Poll a job until it ends, its progress on the bar (and its time left in the element "<bar's id>-eta"
// when the page has one); its result, or its error as an ApiError.
async function pollJob(id, bar) {
  const eta = document.getElementById(bar.id + "-eta");
  try {
    for (let polls = 0; ; polls++) {
      const job = (await apiJson("/v1/jobs/" + id)).data;
      bar.value = job.progress;
      bar.title = timeLeft(job);
      if (eta) {
        eta.textContent = bar.title;
        eta.hidden = !bar.title;
      }
      if (job.state === "succeeded") return job.result;
      if (job.state === "failed") throw new ApiError(job.error.message, job.error.code, job.error.field);
      if (job.state === "cancelled") throw new ApiError("Cancelled.");
      // Short jobs answer fast; long ones are polled four times a second.
      await new Promise((resolve) => setTimeout(resolve, Math.min(250, 40 + 20 * polls)));
    }
  } finally {
    if (eta) eta.hidden = true;
  }
}

// An image the API serves (needs the key): fetched, then shown from a blob: URL.
async function loadImage(img, url) {
  const blob = await (await api(url)).blob();
  const objectUrl = URL.createObjectURL(blob);
  state.blobs.push(objectUrl);
  await new Promise((resolve, reject) => {
    img.onload = resolve;
    img.onerror = () => reject(new ApiError("An image from the server could not be shown."));
    img.src = objectUrl;
  });
}

// A message in the section's own line: kind "" (news), "warning" or "error".
function say(where, text, kind = "") {
  const p = $(where);
  p.textContent = text;
  p.classList.toggle("error", kind === "error");
  p.classList.toggle("warning", kind === "warning");
  if (kind === "error") p.scrollIntoView({ block: "center" });
}

// Run an action; its error is shown next to the control that started it, or beside the control
// of the field it names (FIELD_LINES), in plain words.
async function guarded(where, action) {
  say(where, "");                      // an old error does not outlive the next action
  try {
    await action();
  } catch (err) {
    const line = (err instanceof ApiError && err.field && FIELD_LINES[fieldBase(err.field)]) || where;
    say(where, "");                    // the action's own words ("ranking...") end with it
    say(line, plain(err, where), "error");
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

// A frame's centre: a transforms frame's c2w translation, or a cameras.json entry's position.
const position = (frame) => (frame.transform_matrix ? [0, 1, 2].map((i) => frame.transform_matrix[i][3]) : frame.position);
const column = (frame, j) => [0, 1, 2].map((i) => frame.transform_matrix[i][j]);
const cardLabel = (index, rank) => `candidate ${index} · rank #${rank}`;

// ------------------------------------------------------------------ camera files

const CAMERA_KEYS = ["fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "k1", "k2", "p1", "p2"];

// The frames of a camera file, as the service reads them: a list of frames, a transforms.json
// ({"frames": [...]}, its camera keys defaults for every frame), a reference trainer's
// cameras.json, or the sidecar phd train wrote (its training_cameras). Anything else is an
// error naming what the file holds, never "0 poses".
function framesOf(text, name) {
  let data;
  try {
    data = JSON.parse(text);
  } catch (err) {
    throw new ApiError(`${name} is not valid JSON (${err.message}).`);
  }
  if (data && !Array.isArray(data) && typeof data === "object" && Array.isArray(data.training_cameras)) {
    data = data.training_cameras;                      // a phd train sidecar
  }
  let frames = data, defaults = {};
  if (!Array.isArray(data)) {
    if (data === null || typeof data !== "object") throw new ApiError(`${name} holds no poses: expected a list of frames or an object with a "frames" list.`);
    if (!("frames" in data)) {
      const keys = Object.keys(data).slice(0, 6).map((k) => `"${k}"`).join(", ") || "none";
      throw new ApiError(`${name} has no "frames" list (its keys: ${keys}): expected a transforms.json with "frames", a cameras.json or a list of frames.`);
    }
    if (!Array.isArray(data.frames)) throw new ApiError(`"frames" in ${name} is not a list.`);
    frames = data.frames;
    defaults = Object.fromEntries(Object.entries(data).filter(([k]) => CAMERA_KEYS.includes(k)));
  }
  if (frames.length === 0) throw new ApiError(`${name} holds an empty list of poses.`);
  frames.forEach((f, i) => {
    if (f === null || typeof f !== "object" || Array.isArray(f)) throw new ApiError(`Pose ${i} of ${name} is not an object.`);
    if (!("transform_matrix" in f) && !isEntry(f)) {
      const keys = Object.keys(f).slice(0, 6).map((k) => `"${k}"`).join(", ") || "none";
      throw new ApiError(`Pose ${i} of ${name} has no "transform_matrix" (nor a cameras.json "position" and "rotation"); its keys: ${keys}.`);
    }
  });
  return frames.map((f) => Object.assign({}, defaults, f));
}

// A reference trainer's cameras.json entry (it always says its image size).
const isEntry = (f) => Array.isArray(f.position) && Array.isArray(f.rotation);
const hasSize = (f) => isEntry(f) || (f.w !== undefined && f.h !== undefined);
// True when some frame does not say its image size.
const lacksSize = (frames) => !frames.every(hasSize);

// Frames with the size fields' width and height where they give none; an error naming the fields,
// on the field the prefix names (so the target views' is said beside their control: FIELD_LINES).
function sized(frames, prefix) {
  if (!lacksSize(frames)) return frames;
  const w = Number($(prefix + "-width").value), h = Number($(prefix + "-height").value);
  if (!(w >= 1 && h >= 1)) {
    throw new ApiError("These poses do not say their image size: fill in width and height (in pixels).", "page", prefix);
  }
  return frames.map((f) => (hasSize(f) ? f : Object.assign({ w, h }, f)));
}

// ------------------------------------------------------------------ models

async function loadModels(selectId, selectB) {
  state.models = (await apiJson("/v1/models")).data.models;
  for (const [id, keep] of [["model-select", selectId], ["model-b-select", selectB || $("model-b-select").value]]) {
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

// The downscale that renders the model's training images at about 100 px (never below):
// enough for a heat map to show where the model is unsure, fast enough to try things.
function defaultDownscale(frames) {
  const sizes = frames.filter((f) => f.w && f.h).map((f) => Math.min(f.w, f.h));
  return sizes.length ? Math.max(1, Math.floor(Math.min(...sizes) / 100)) : 1;
}

async function modelChosen() {
  const model = currentModel();
  const changed = (model ? model.id : null) !== state.modelId;
  state.modelId = model ? model.id : null;
  if (changed) state.viewReady = false;       // until the 3D view has drawn this model
  state.training = [];
  state.up = [0, 0, 1];
  if (changed) {                              // the last model's messages are not about this one
    $("model-warning").hidden = true;
    say("model-message", "");
  }
  $("calibrate").disabled = Boolean(model) && !calibratable(model);   // the warning says why
  $("calibrate").title = $("calibrate").disabled ? "This model has no training cameras: see the warning above." : "";
  showCalibrateB();
  if (!model && state.models.length) {
    $("model-info").textContent = "No model chosen.";
  } else if (!model) {
    $("model-info").textContent = "No model yet: upload one below.";
    $("upload-details").open = true;
  } else {
    const cal = model.calibration;
    $("model-info").textContent = model.kind + ", " + model.num_units + " dropout units, " +
      (model.num_training_cameras ? model.num_training_cameras + " training cameras" : "no training cameras") +
      (model.camera_format ? " (" + model.camera_format + ")" : "") + ", " +
      (cal ? "calibrated: r_drop = " + cal.r_drop : model.has_training_cameras ?
        "not calibrated yet: press Calibrate before ranking" : "so it cannot be calibrated");
    if (model.has_training_cameras) {
      const cameras = (await apiJson("/v1/models/" + model.id + "/cameras")).data;
      state.training = cameras.frames;
      state.up = cameras.up;
    } else if (changed) {                     // said once, when the model is chosen: the one place for this advice
      $("model-warning").textContent = "This model has no training cameras. " + NO_CAMERAS_ADVICE;
      $("model-warning").hidden = false;
    }
    // What reading the model noted, but the service's note that it has no cameras (NO_CAMERAS_NOTE):
    // the warning above says that already, with what to do.
    const notes = ((model.details && model.details.notes) || []).filter((n) => !n.startsWith("the model has no training cameras"));
    if (notes.length) $("model-info").textContent += ". Noted on reading it: " + notes.join(" ");
  }
  if (changed) {
    modelOfCapture(model);                    // a capture's rounds stay in the 3D view only over its own models
    const scale = String(defaultDownscale(state.training));
    $("cal-downscale").value = scale;
    $("rank-downscale").value = scale;
    await updateCandidates();
    if (view3d() && model) {
      // false when the view cannot draw (no WebGL: it says why in its own status line) or another
      // model was chosen meanwhile
      const drawn = await view3d().mount($("view3d"), { modelId: model.id, headers: authHeaders() });
      state.viewReady = drawn && state.modelId === model.id;
    }
  } else {
    drawPlots();
  }
  prefillSizes();
}

const authHeaders = () => (state.key ? { Authorization: "Bearer " + state.key } : {});

// The files to upload: those picked (files and a folder) or dropped, each with its path.
function pickedFiles() {
  if (state.dropped) return state.dropped;
  const files = [...$("upload-file").files].map((file) => ({ file, path: file.name }));
  return files.concat([...$("upload-folder").files].map((file) => ({ file, path: file.webkitRelativePath || file.name })));
}

// What a folder's upload leaves behind, and why: photos (the model needs none) and what `phd` keeps
// in its .phd-cache/ but the calibrations (the service uses one made for this model, on its
// cameras: docs/service.md), since the rest is worked out again by the service.
const LEFT_OUT = [
  { test: (path) => /\.(png|jpe?g|exr|webp|tiff?|bmp|mp4|mov)$/i.test(path), what: "image", why: "the model needs no photos" },
  { test: (path) => /phd-cache\//.test(path) && !/phd-cache\/calibration-[^/]*\.json$/.test(path),
    what: "other .phd-cache file", why: "results the service works out itself" },
];
const leftOut = (path) => LEFT_OUT.find((rule) => rule.test(path)) || null;
const plural = (count, word) => `${count} ${word}${count === 1 ? "" : "s"}`;

// The line under the pickers: what goes up (the first few named), what stays behind and why.
function describePicked() {
  const picked = pickedFiles();
  if (picked.length <= 1) {
    $("upload-picked").textContent = picked.length ? "Uploads 1 file: " + picked[0].path : "";
    return;
  }
  const sent = picked.filter((p) => !leftOut(p.path));
  const behind = LEFT_OUT.map((rule) => [rule, picked.filter((p) => leftOut(p.path) === rule).length])
    .filter(([, count]) => count).map(([rule, count]) => `${plural(count, rule.what)} (${rule.why})`);
  $("upload-picked").textContent = `Uploads ${plural(sent.length, "file")}: ` +
    sent.slice(0, 4).map((p) => p.path).join(", ") + (sent.length > 4 ? ", ..." : "") + "." +
    (behind.length ? " Leaves out " + behind.join(" and ") + "." : "");
}

// What a drop holds, folders walked: [{file, path}].
async function droppedFiles(dataTransfer) {
  const entries = [...dataTransfer.items].map((item) => item.webkitGetAsEntry && item.webkitGetAsEntry()).filter(Boolean);
  if (entries.length === 0) return [...dataTransfer.files].map((file) => ({ file, path: file.name }));
  const out = [];
  const walk = async (entry, prefix) => {
    if (entry.isFile) {
      out.push({ file: await new Promise((resolve, reject) => entry.file(resolve, reject)), path: prefix + entry.name });
      return;
    }
    const reader = entry.createReader();
    for (;;) {
      const batch = await new Promise((resolve, reject) => reader.readEntries(resolve, reject));
      if (batch.length === 0) break;
      for (const child of batch) await walk(child, prefix + entry.name + "/");
    }
  };
  for (const entry of entries) await walk(entry, "");
  return out;
}

async function readUploadCameras() {
  state.uploadCameras = null;
  $("upload-size").hidden = true;
  const file = $("upload-cameras").files[0];
  if (!file) return;
  const text = await file.text();
  const frames = framesOf(text, file.name);           // a file the service would refuse is named now
  state.uploadCameras = { text, frames, name: file.name };
  $("upload-size").hidden = !lacksSize(frames);
}

const stem = (path) => path.replace(/^.*\//, "").replace(/\.[^.]*$/, "");

// The upload's form: one model file (with its cameras), a zip, or a folder's files by path. A
// model picked with a camera file that is not its sidecar (<stem>.json) sends that file as its
// training cameras.
async function uploadForm() {
  let picked = pickedFiles().filter((p) => !leftOut(p.path) || pickedFiles().length === 1);
  if (picked.length === 0) throw new ApiError("Choose the model's files first (or drop them on the box).");
  const json = picked.filter((p) => /\.json$/i.test(p.path));
  const model = picked.filter((p) => !/\.json$/i.test(p.path));
  let cameras = state.uploadCameras;
  if (picked.length === 2 && json.length === 1 && stem(json[0].path) !== stem(model[0].path) && !cameras) {
    const text = await json[0].file.text();
    cameras = { text, frames: framesOf(text, json[0].path) };
    $("upload-size").hidden = !lacksSize(cameras.frames);
    picked = model;
  }
  const form = new FormData();
  if (picked.length === 1 && /\.zip$/i.test(picked[0].path)) form.append("archive", picked[0].file, picked[0].path);
  else if (picked.length === 1) form.append("file", picked[0].file, picked[0].path);
  else picked.forEach((p) => form.append("files", p.file, p.path));
  if (cameras) {
    form.append("cameras", lacksSize(cameras.frames) ? JSON.stringify(sized(cameras.frames, "upload")) : cameras.text);
  }
  if ($("upload-name").value.trim()) form.append("name", $("upload-name").value.trim());
  if ($("upload-other-capture").checked) form.append("other_capture", "true");
  return { form, count: picked.length };
}

async function upload(event) {
  event.preventDefault();
  const { form, count } = await uploadForm();
  const keepA = currentModel();
  say("upload-message", `uploading ${count} file${count > 1 ? "s" : ""}...`);
  $("upload-run").disabled = true;
  let info;
  try {
    info = (await apiJson("/v1/models", { method: "POST", body: form })).data;
  } catch (err) {
    // Cameras that see none of the model: offer the override the message names.
    if (err instanceof ApiError && err.code === "cameras_of_another_capture") $("upload-other-capture-row").hidden = false;
    throw err;
  } finally {
    $("upload-run").disabled = false;
  }
  state.dropped = null;
  $("upload-other-capture").checked = false;          // the override was for these files only
  $("upload-other-capture-row").hidden = true;
  // Messages about the models before this upload (a failed calibration, a warning) are done with.
  $("model-warning").hidden = true;
  say("model-message", "");
  // The model chosen as A stays A (its ranking too): the new one becomes model B.
  await loadModels(keepA ? keepA.id : info.id, keepA ? info.id : undefined);
  const where = keepA ? "It is model B for selection; choose it under Model to rank it." : "It is the chosen model.";
  if (info.note) {
    say("upload-message", `${info.name}: ${info.note}. ${where}`);
  } else if (!info.has_training_cameras) {
    // Chosen, the warning under Model gives the advice; as model B, this is the one place for it.
    say("upload-message", `Uploaded ${info.name}, but it has no training cameras. ` +
      (keepA ? NO_CAMERAS_ADVICE : "What to add is said under Model above."), "warning");
  } else {
    say("upload-message", `Uploaded ${info.name}: ${info.kind}, ${info.num_training_cameras} training cameras` +
      (info.camera_format ? ` (${info.camera_format})` : "") +
      (info.calibration ? `, calibrated: r_drop = ${info.calibration.r_drop} (the calibration phd stored in its .phd-cache/)` : "") +
      ". " + where);
  }
}

// Calibrate a model with section 1's samples and downscale, reported in the line `where` and the
// bar `bar`: the chosen model from section 1, model B from section 4 (A stays chosen, its ranking shown).
async function calibrate(model, where, bar) {
  if (!model) throw new ApiError("Choose or upload a model first.");
  say(where, "calibrating " + model.name + "...");
  for (const id of ["calibrate", "calibrate-b"]) $(id).disabled = true;   // one calibration at a time from this page
  let result;
  try {
    result = await runJob("/v1/models/" + model.id + "/calibrate",
      { samples: Number($("cal-samples").value), downscale: Number($("cal-downscale").value) }, bar);
  } finally {
    $("calibrate-b").disabled = false;
    $("calibrate").disabled = Boolean(currentModel()) && !calibratable(currentModel());
  }
  say(where, "calibrated " + model.name + ": r_drop = " + result.r_drop);
  await loadModels($("model-select").value);   // the model chosen now, which may be another one by this time
  // The 3D view explains the calibrated model again (fragility is measured at its new ratio).
  if (view3d() && state.viewReady && state.modelId === model.id) await view3d().refresh();
}

const modelB = () => state.models.find((m) => m.id === $("model-b-select").value) || null;
const calibratable = (model) => model.has_training_cameras;   // calibration renders the training views

// "Calibrate model B" beside Select: for a model B that is not calibrated and can be (it has cameras).
function showCalibrateB() {
  const b = modelB();
  $("calibrate-b").hidden = !(b && !b.calibration && calibratable(b) && b.id !== $("model-select").value);
}

async function deleteModel() {
  const model = currentModel();
  if (!model || !window.confirm("Delete " + model.name + "?")) return;
  await api("/v1/models/" + model.id, { method: "DELETE" });
  say("model-message", "deleted " + model.name);
  await loadModels();
}

// ------------------------------------------------------------------ candidates

function captureFrame() {
  const frames = state.training;
  const model = currentModel();
  if (frames.length === 0) {
    const b = model && model.bounds;
    const center = b ? mul(add(b.min, b.max), 0.5) : [0, 0, 0];
    const radius = b ? Math.max(norm(sub(b.max, b.min)), 1e-3) * 1.5 : 4;
    return { center, up: state.up, radius };
  }
  const A = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  let rhs = [0, 0, 0];
  for (const f of frames) {
    const p = position(f);
    const d = unit(mul(column(f, 2), -1));  // OpenGL: the camera looks along -z
    for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) A[i][j] += (i === j ? 1 : 0) - d[i] * d[j];
    rhs = add(rhs, sub(p, mul(d, dot(d, p))));
  }
  let center = solve3(A, rhs);
  if (!center) center = mul(frames.map(position).reduce(add, [0, 0, 0]), 1 / frames.length);
  const distances = frames.map((f) => norm(sub(position(f), center))).sort((a, b) => a - b);
  return { center, up: state.up, radius: distances[Math.floor(distances.length / 2)] };
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

// Width and height fields for camera files without an image size (candidates, target views),
// filled with the size of the model's training images when the model has them.
function prefillSizes() {
  const sizedFrame = state.training.find((f) => f.w && f.h);
  for (const prefix of ["cand", "targets"]) {
    if (sizedFrame && !$(prefix + "-width").value && !$(prefix + "-height").value) {
      $(prefix + "-width").value = sizedFrame.w;
      $(prefix + "-height").value = sizedFrame.h;
    }
    $(prefix + "-size-hint").textContent = "These poses do not say their image size: give it in pixels" +
      (sizedFrame ? ` (filled in: the size of the model's training images, ${sizedFrame.w} x ${sizedFrame.h}).` : ".");
  }
}

async function updateCandidates() {
  const mode = document.querySelector("input[name=cand-mode]:checked").value;
  $("generate-options").hidden = mode !== "generate";
  $("file-options").hidden = mode !== "file";
  $("cand-size").hidden = true;
  state.candidates = [];
  state.spec = null;
  forgetRanking();                    // a ranking belongs to the candidates it ranked
  state.rankToken++;                  // and a rank still running ranks other candidates now
  $("cand-info").textContent = "";
  try {
    if (mode === "generate") {
      state.spec = candidateSpec();
      $("cand-info").textContent = state.spec.count + " " + state.spec.generator + " poses, made by the service " +
        (state.training.length ? "around the training cameras" : "around the model's splats") +
        " when you rank; the plots show the poses it returns";
    } else {
      const file = $("cand-file").files[0];
      if (file) {
        state.candidates = framesOf(await file.text(), file.name);
        $("cand-size").hidden = !lacksSize(state.candidates);
        prefillSizes();
        $("cand-info").textContent = state.candidates.length + " poses from " + file.name;
      } else {
        $("cand-info").textContent = "choose a JSON file of candidate poses";
      }
    }
  } finally {
    drawPlots();
  }
}

// ------------------------------------------------------------------ target views

// The optional target views file (where the model will be looked at from), read as a candidates
// file is, drawn in the 3D view and sent as the rank request's targets. A ranking belongs to the
// target views it was made for, as to its candidates.
async function updateTargets() {
  const file = $("targets-file").files[0];
  state.targets = [];
  forgetRanking();
  state.rankToken++;
  $("targets-size").hidden = true;
  $("targets-info").textContent = "";
  $("targets-clear").hidden = !file;          // for a file that could not be read too
  try {
    if (file) {
      state.targets = framesOf(await file.text(), file.name);
      $("targets-size").hidden = !lacksSize(state.targets);
      prefillSizes();
      $("targets-info").textContent = `${state.targets.length} target pose${state.targets.length > 1 ? "s" : ""} ` +
        `from ${file.name}: the coverage strategies value a candidate by what it fixes in these views`;
    }
  } finally {
    drawTargets();
  }
}

// The target views in the 3D view, at the size fields' size where they say none (drawn once
// those are filled in: the frusta's shape needs it).
function drawTargets() {
  if (!view3d()) return;
  let frames = [];
  try {
    frames = sized(state.targets, "targets");
  } catch (_) { /* no size yet: the hint above the fields asks for it */ }
  view3d().showTargets(frames);
}

function clearTargets() {
  $("targets-file").value = "";
  return updateTargets();
}

// The rank request's target views ({} for none), sized as the candidates are. A file chosen but
// not read is an error, not a ranking without it.
function targetBody() {
  if ($("targets-file").files.length && state.targets.length === 0) {
    throw new ApiError("The target views file could not be read: choose another, or clear it to rank for every view alike.",
      "page", "targets");
  }
  return state.targets.length ? { targets: sized(state.targets, "targets") } : {};
}

// ------------------------------------------------------------------ plots

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
      title.textContent = view ? `${cardLabel(i, view.rank)}, score ${fmt(view.score)}` : `candidate ${i} (not returned)`;
      dotEl.append(title);
      dotEl.addEventListener("click", () => pickCandidate(i));
      svg.append(dotEl);
      if (view && view.rank <= 3) {
        const label = svgEl("text", { x: x + 7, y: y - 7, class: "label" });
        label.textContent = String(view.rank);
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

// A candidate picked in a plot, a card or the 3D view: its card, its dots and its frustum marked.
function pickCandidate(index, fromView = false) {
  focusCard(index);
  if (view3d() && !fromView) view3d().select(Number(index));
  document.querySelectorAll(".plot circle.picked").forEach((c) => c.classList.remove("picked"));
  document.querySelectorAll(`.plot circle[data-index="${index}"]`).forEach((c) => c.classList.add("picked"));
}

// ------------------------------------------------------------------ rank

function sizeOptions(prefix) {
  const downscale = Number($(prefix + "-downscale").value);
  return downscale > 0 ? { downscale } : {};
}

// The candidate poses of a rank request: a generator spec, or the file's frames (sized).
function candidateBody() {
  if (state.spec !== null) return { candidates: state.spec };
  if (state.candidates.length === 0) throw new ApiError("No candidate poses yet: choose a JSON file in section 2.");
  return { cameras: sized(state.candidates, "cand") };
}

async function rank(event) {
  event.preventDefault();
  say("targets-message", "");             // an old error beside the target views goes, as the section's own does
  const model = currentModel();
  if (!model) throw new ApiError("Choose or upload a model first.");
  const body = Object.assign({ samples: Number($("rank-samples").value), seed: Number($("rank-seed").value),
    heatmaps: "files" }, sizeOptions("rank"), candidateBody(), targetBody());
  if ($("rank-strategy").value) body.strategy = $("rank-strategy").value;
  if ($("rank-topk").value) body.top_k = Number($("rank-topk").value);
  say("rank-message", "ranking " + (state.spec ? state.spec.count : state.candidates.length) + " candidates" +
    forTargets(body.targets ? body.targets.length : 0) + "...");
  forgetRanking();                        // no stale cards or frusta while the new ranking runs
  const token = ++state.rankToken;
  $("rank-run").disabled = true;
  $("rank-cancel").hidden = false;
  let r;
  try {
    r = await runJob("/v1/models/" + model.id + "/rank", body, $("rank-progress"), (id) => { state.job = id; });
  } finally {
    state.job = null;
    $("rank-run").disabled = false;
    $("rank-cancel").hidden = true;
  }
  // The model, the candidates or the targets changed while the job ran: its order belongs to them, not to what is chosen now.
  if (token !== state.rankToken || !currentModel() || currentModel().id !== model.id) {
    say("rank-message", "That ranking was for another model, other candidates or other target views than those chosen now, " +
      "so it is not shown: press \"Rank\" again.", "warning");
    return;
  }
  state.ranking = Object.assign({}, r, { modelId: model.id });
  $("rank-summary").textContent = `${r.views.length} of ${r.num_candidates} candidates, in the order to capture them${forTargets(r.num_targets)}; ` +
    `strategy ${r.strategy} (${r.rule}), dropout ratio ${r.dropout_ratio} (${r.ratio_source === "calibration" ? "calibrated" : "given"}), ` +
    `${r.samples} samples, rendered at ${r.width} x ${r.height} px; ` +
    `heat maps share one scale: yellow = zeta ${fmt(r.heatmap_vmax)}, dark blue = 0`;
  drawPlots();
  // With the user's own list: the unreturned ones too.
  if (view3d()) view3d().showRanking(r, body.cameras ? { candidates: body.cameras } : {});
  showDownload(r, model);
  await drawRankGrid(r);
  say("rank-message", "Ranked: capture candidate " + r.views[0].index + " first.");
}

// " for the N target views" of a ranking made for them, "" of one made for every view alike.
const forTargets = (count) => (count ? ` for the ${count} target view${count > 1 ? "s" : ""}` : "");

// No ranking: its cards, summary, download row, plotted dots and frusta go with it.
function forgetRanking() {
  state.ranking = null;
  drawPlots();
  $("rank-grid").replaceChildren();
  $("rank-summary").textContent = "";
  $("poses-row").hidden = true;
  if (view3d()) view3d().clear();
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
    const [x, y, z] = position(v.camera).map((c) => fmt(c, 3));
    const look = unit(mul(column(v.camera, 2), -1)).map((c) => fmt(c, 2));
    return el("li", { class: "card", "data-index": v.index, "data-rank": v.rank },
      el("div", { class: "pair" },
        el("figure", {}, render, el("figcaption", { text: "render" })),
        el("figure", {}, heat, el("figcaption", { text: "zeta" }))),
      el("p", { class: "title", text: cardLabel(v.index, v.rank) }),
      el("dl", {},
        el("dt", { text: "score" }), el("dd", { class: "score", text: fmt(v.score) }),
        el("dt", { text: "sigma_max" }), el("dd", { text: fmt(v.sigma_max) }),
        el("dt", { text: "sigma_mean" }), el("dd", { text: fmt(v.sigma_mean) }),
        el("dt", { text: "centre" }), el("dd", { class: "pose", text: `${x}, ${y}, ${z}` }),
        el("dt", { text: "looks" }), el("dd", { class: "pose", text: `${look.join(", ")}` })));
  }));
  grid.querySelectorAll("li").forEach((li) => li.addEventListener("click", () => pickCandidate(li.dataset.index)));
  await Promise.all(loads);
}

async function cancelRank() {
  if (state.job) await api("/v1/jobs/" + state.job, { method: "DELETE" });
}

// ------------------------------------------------------------------ poses to capture

// The download row after a ranking: the model's own convention first, the first k poses.
function showDownload(result, model) {
  const own = [result.camera_format, model.camera_format].find((f) => state.formats.some((o) => o.name === f)) || "nerfstudio";
  $("poses-format").replaceChildren(...state.formats.map((f) => el("option", {
    value: f.name, text: f.title + (f.name === own ? " (the model's own)" : "") })));
  $("poses-format").value = own;
  $("poses-topk").max = result.views.length;
  $("poses-topk").value = result.views.length;
  $("poses-row").hidden = false;
}

// The first k ranked poses as the file(s) a capture tool reads, written by the service with the
// code `phd rank --export` uses; saved through the browser's download.
async function downloadPoses() {
  const r = state.ranking;
  if (!r) throw new ApiError("Rank first: the poses to download are the ranked ones.");
  const k = Math.max(1, Math.min(r.views.length, Number($("poses-topk").value) || r.views.length));
  const views = r.views.slice(0, k);
  const response = await api("/v1/models/" + r.modelId + "/poses", { method: "POST", json: {
    cameras: views.map((v) => v.camera), indices: views.map((v) => v.index), format: $("poses-format").value } });
  const name = (/filename="([^"]+)"/.exec(response.headers.get("Content-Disposition") || "") || [])[1] || "poses";
  const url = URL.createObjectURL(await response.blob());
  const link = el("a", { href: url, download: name });
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
  say("rank-message", `Saved the first ${k} poses as ${name}.`);
}

// ------------------------------------------------------------------ select

async function select(event) {
  event.preventDefault();
  const a = currentModel(), bId = $("model-b-select").value;
  if (!a || !bId) throw new ApiError("Choose two models: model A under Model, model B here.");
  if (a.id === bId) throw new ApiError("Model B must be another model than model A.");
  // Generated poses exist once the service made them: select over the ranked views' poses.
  const shown = shownCandidates();
  if (shown.length === 0) {
    throw new ApiError(state.spec ? "Rank first: the service makes the generated poses when it ranks." :
      "No candidate poses yet: choose a JSON file in section 2.");
  }
  const cameras = state.spec === null ? sized(shown.map((c) => c.frame), "cand") : shown.map((c) => c.frame);
  say("select-message", "selecting over " + cameras.length + " views...");
  $("select-grid").replaceChildren();
  $("select-summary").textContent = "";
  const body = Object.assign({ model_a: a.id, model_b: bId, cameras, rule: $("select-rule").value || undefined,
    samples: Number($("rank-samples").value), seed: Number($("rank-seed").value), images: "files", both_images: true },
  sizeOptions("rank"));
  const result = await runJob("/v1/select", body, $("select-progress"));
  const names = { a: a.name, b: (state.models.find((m) => m.id === bId) || { name: "B" }).name };
  $("select-summary").textContent = `A (${names.a}) trusted for ${result.counts.a} views, B (${names.b}) for ${result.counts.b}; ` +
    `rule ${result.rule} (the lower score is trusted)`;
  // A view is named as its candidate was in the ranking: its index and rank.
  const ranks = new Map((state.ranking ? state.ranking.views : []).map((v) => [v.index, v.rank]));
  const loads = [];
  $("select-grid").replaceChildren(...result.views.map((v) => {
    const index = shown[v.index].index;
    const label = ranks.has(index) ? cardLabel(index, ranks.get(index)) : `candidate ${index}`;
    const urls = v.choice === "a" ? { a: v.image_url, b: v.other_image_url } : { a: v.other_image_url, b: v.image_url };
    const figures = ["a", "b"].map((key) => {
      const img = el("img", { class: "render", alt: `model ${key.toUpperCase()} render of candidate ${index}` });
      if (urls[key]) loads.push(loadImage(img, urls[key]));
      return el("figure", { class: v.choice === key ? "chosen" : "" }, img,
        el("figcaption", { text: `${key.toUpperCase()}: ${fmt(v["score_" + key], 3)}${v.choice === key ? " (trusted)" : ""}` }));
    });
    const li = el("li", { class: "card", "data-index": index, "data-choice": v.choice },
      el("div", { class: "pair" }, ...figures), el("p", { class: "title", text: `${label}: trust ${v.choice.toUpperCase()}` }));
    if (ranks.has(index)) li.dataset.rank = ranks.get(index);
    return li;
  }));
  await Promise.all(loads);
  say("select-message", "Selection done.");
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
    state.formats = (schemas.PosesRequest.properties.format.examples || []).map((name) => ({ name, title: FORMAT_TITLES[name] || name }));
  } catch (_) { /* the strategy stays free text, the rule list empty: the server's defaults apply */ }
}

const FORMAT_TITLES = { nerfstudio: "transforms.json (nerfstudio)", blender: "transforms_train.json (Blender)",
  colmap: "COLMAP images.txt + cameras.txt (zip)", "3dgs-output": "cameras.json (reference 3DGS)" };

function start() {
  $("api-key").value = state.key;
  $("view3d-section").hidden = !view3d();
  if (view3d()) view3d().onPick((index) => pickCandidate(index, true));
  $("key-form").addEventListener("submit", (e) => {
    e.preventDefault();
    state.key = $("api-key").value.trim();
    localStorage.setItem("phd-api-key", state.key);
    say("model-message", "");
    state.modelId = null;                    // set up again: the 3D view takes the new key's headers
    guarded("message", () => loadModels($("model-select").value).then(loadCaptures)
      .then(() => say("message", "key saved in this browser")));
  });
  $("refresh-models").addEventListener("click", () => guarded("model-message", () => loadModels($("model-select").value)));
  $("model-select").addEventListener("change", () => guarded("model-message", modelChosen));
  $("delete-model").addEventListener("click", () => guarded("model-message", deleteModel));
  $("calibrate").addEventListener("click", () => guarded("model-message", () =>
    calibrate(currentModel(), "model-message", $("cal-progress"))));
  $("calibrate-b").addEventListener("click", () => guarded("select-message", () =>
    calibrate(modelB(), "select-message", $("select-progress"))));
  $("model-b-select").addEventListener("change", () => { say("select-message", ""); showCalibrateB(); });
  $("upload-form").addEventListener("submit", (e) => guarded("upload-message", () => upload(e)));
  for (const id of ["upload-file", "upload-folder"]) {
    $(id).addEventListener("change", () => { state.dropped = null; describePicked(); });
  }
  $("upload-cameras").addEventListener("change", () => guarded("upload-message", readUploadCameras));
  const zone = $("drop-zone");
  zone.addEventListener("dragover", (e) => { e.preventDefault(); zone.classList.add("over"); });
  zone.addEventListener("dragleave", () => zone.classList.remove("over"));
  zone.addEventListener("drop", (e) => {
    e.preventDefault();
    zone.classList.remove("over");
    guarded("upload-message", async () => { state.dropped = await droppedFiles(e.dataTransfer); describePicked(); });
  });
  document.querySelectorAll("input[name=cand-mode], #generate-options input, #generate-options select, #cand-file")
    .forEach((input) => input.addEventListener("change", () => guarded("cand-message", updateCandidates)));
  $("targets-file").addEventListener("change", () => guarded("targets-message", updateTargets));
  $("targets-clear").addEventListener("click", () => guarded("targets-message", clearTargets));
  for (const id of ["targets-width", "targets-height"]) $(id).addEventListener("change", drawTargets);
  $("rank-form").addEventListener("submit", (e) => guarded("rank-message", () => rank(e)));
  $("rank-cancel").addEventListener("click", () => guarded("rank-message", cancelRank));
  $("poses-download").addEventListener("click", () => guarded("rank-message", downloadPoses));
  $("select-form").addEventListener("submit", (e) => guarded("select-message", () => select(e)));
  startCaptures();
  readChoices();
  guarded("message", async () => {             // a missing key is said beside the key field, before any call
    const health = (await apiJson("/health")).data;
    if (health.key_required && !state.key) {
      say("message", "This server asks for an API key: type it above and press \"Use key\".", "warning");
      return;
    }
    await loadModels();
    await loadCaptures();
  });
}

document.addEventListener("DOMContentLoaded", start);
