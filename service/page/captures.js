// The page's Captures section (issue 49, docs/service.md): the capture loop's rounds as a table
// and two charts (test PSNR and sigma-max-bar by round), each round's captured cameras in the 3D
// view in its own colour with the capture's latest model, and Train / Next views.
// A classic script loaded after app.js: it uses app.js's helpers (api calls, jobs, messages,
// the model list and the 3D view) and app.js calls loadCaptures, startCaptures and
// modelOfCapture from here.
"use strict";

const loop = {
  captures: [],      // GET /v1/captures
  shown: null,       // the CaptureInfo the section shows
  token: 0,          // raised when another capture is chosen: an older poll or job does not draw
};

const BUSY = ["reconstructing", "registering"];
const CAPTURE_POLL_MS = 1000;    // a capture busy with a job the page did not start: read again this often

// The models trained on a capture, round by round.
const capturedModels = (info) => info.rounds.filter((r) => r.train).map((r) => r.train.model_id);

async function loadCaptures() {
  loop.captures = (await apiJson("/v1/captures")).data.captures;
  const select = $("capture-select");
  const keep = select.value;
  select.replaceChildren(el("option", { value: "", text: loop.captures.length ? "choose a capture" : "none yet" }),
    ...loop.captures.map((c) => el("option", { value: c.id, text: `${c.name} (${c.state}, ${plural(c.rounds.length, "round")})` })));
  if (loop.captures.some((c) => c.id === keep)) select.value = keep;
  if (!loop.captures.length) {
    $("capture-info").textContent = "No capture yet: make one from photos with phd loop, or POST /v1/captures " +
      "(its rounds show here).";
  }
}

async function captureChosen() {
  const id = $("capture-select").value;
  const token = ++loop.token;
  loop.shown = null;
  say("capture-message", "");
  $("capture-rounds").hidden = true;
  $("photos-add").disabled = true;
  $("capture-info").textContent = "";
  if (view3d()) view3d().showCapture($("view3d"), null);
  if (!id) return;
  await openCapture((await apiJson("/v1/captures/" + id)).data, token);
}

// A capture in the section: its facts and rounds; once ready, in the 3D view with its latest model.
// Busy (structure-from-motion on new photos), its state is said and it is read again until ready.
async function openCapture(info, token) {
  loop.shown = info;
  describeCapture(info);
  if (BUSY.includes(info.state)) {
    say("capture-message", `${info.name} is ${info.state} (structure-from-motion): shown when it is done...`);
    info = await untilReady(info, token);
    if (token !== loop.token) return;
    say("capture-message", "");
    await loadCaptures();            // its state in the list too
    loop.shown = info;
    describeCapture(info);
  }
  if (info.state === "failed") {
    say("capture-message", `${info.name} failed its first reconstruction: ` +
      (info.error ? plainText(info.error.message) : "the service gave no reason") + ". Make a new one.", "error");
    return;
  }
  await drawCapture(info, token);
}

// The capture once it is no longer busy: its job polled (progress on the bar) when the page
// knows it (the answer that started it names it), else the capture read again every second.
async function untilReady(info, token) {
  const bar = $("capture-progress");
  bar.hidden = false;
  bar.value = 0;
  try {
    if (info.job) await pollJob(info.job, bar);
    while (BUSY.includes(info.state) && token === loop.token) {
      if (!info.job) await new Promise((resolve) => setTimeout(resolve, CAPTURE_POLL_MS));
      info = (await apiJson("/v1/captures/" + info.id)).data;
    }
    return info;
  } finally {
    bar.hidden = true;
  }
}

function describeCapture(info) {
  const trained = capturedModels(info).length;
  $("capture-info").textContent = `${info.name}: ${info.state}, ${plural(info.num_photos, "photo")} registered in ` +
    `${plural(info.rounds.length, "round")}, ${plural(info.test_photos.length, "test photo")} held out of training` +
    (info.test_photos.length ? ` (${info.test_photos.join(", ")})` : "") + `; ${plural(trained, "model")} trained`;
  drawRounds(info);
  drawChart($("chart-psnr"), info.rounds.map((r) => r.train && r.train.test_psnr), 4);
  drawChart($("chart-sigma"), info.rounds.map((r) => r.train && r.train.sigma_max_bar), 3);
  $("capture-rounds").hidden = false;
  $("capture-train").disabled = info.state !== "ready";
  $("photos-add").disabled = info.state !== "ready";
  $("capture-next").disabled = info.state !== "ready" || !info.model_id;
  $("capture-next").title = info.model_id ? "" : "Train first: the next views are ranked with the capture's latest model.";
}

// One row per round; a round not trained has dashes where its model's numbers would be.
function drawRounds(info) {
  const modelName = (id) => (state.models.find((m) => m.id === id) || { name: id }).name;
  $("rounds-table").tBodies[0].replaceChildren(...info.rounds.map((r) => {
    const t = r.train;
    const cells = [String(r.round), String(r.photos.length), String(r.registered.length),
      r.not_registered.length ? r.not_registered.join(", ") : "-", t ? modelName(t.model_id) : "-",
      t ? fmt(t.test_psnr) : "-", t ? fmt(t.sigma_max_bar, 3) : "-", t ? fmt(t.r_drop, 3) : "-",
      t ? t.seconds.toFixed(1) : "-", t ? (t.warm_from ? "warm: " + modelName(t.warm_from) : "scratch") : "-",
      r.next ? String(r.next.length) : "-"];
    const row = el("tr", { "data-round": r.round }, ...cells.map((text) => el("td", { text })));
    row.cells[3].className = "names";
    for (const k of [4, 9]) row.cells[k].className = "model";
    return row;
  }));
}

// A value by round as a small line chart (SVG, 300 x 120): a dot and its value per trained round,
// rounds along the bottom; the scale spans the values shown.
function drawChart(svg, values, digits) {
  const left = 24, right = 276, top = 22, bottom = 94;
  const n = values.length;
  const x = (k) => (n > 1 ? left + (right - left) * k / (n - 1) : (left + right) / 2);
  const known = values.map((v, k) => [k, v]).filter(([, v]) => v !== null && v !== undefined);
  const lo = Math.min(...known.map(([, v]) => v)), hi = Math.max(...known.map(([, v]) => v));
  const y = (v) => (hi > lo ? bottom - (bottom - top) * (v - lo) / (hi - lo) : (top + bottom) / 2);
  const text = (attrs, content) => { const t = svgEl("text", attrs); t.textContent = content; return t; };
  svg.replaceChildren(svgEl("line", { x1: left - 10, y1: bottom + 8, x2: right + 10, y2: bottom + 8, class: "axis" }),
    ...values.map((_, k) => text({ x: x(k), y: 114, "text-anchor": "middle", class: "tick" }, "round " + k)));
  if (!known.length) {
    svg.append(text({ x: 150, y: 58, "text-anchor": "middle", class: "empty" }, "no trained round yet"));
    return;
  }
  svg.append(svgEl("polyline", { points: known.map(([k, v]) => `${x(k)},${y(v)}`).join(" "), class: "line" }));
  for (const [k, v] of known) {
    svg.append(svgEl("circle", { cx: x(k), cy: y(v), r: 4, class: "point", "data-round": k }),
      text({ x: x(k), y: y(v) - 9, "text-anchor": k === 0 && n > 1 ? "start" : k === n - 1 && n > 1 ? "end" : "middle",
        class: "value", "data-round": k }, fmt(v, digits)));
  }
}

// The capture in the 3D view: its rounds' cameras first (the view's framing takes them in), then
// its latest model chosen in section 1 as any model is; with none yet, the cameras alone.
async function drawCapture(info, token) {
  if (view3d()) view3d().showCapture($("view3d"), info);
  if (info.model_id) {
    await loadModels(info.model_id);
    return;
  }
  $("model-select").value = "";
  await modelChosen();
  if (view3d() && token === loop.token) await view3d().mount($("view3d"), { modelId: null, headers: authHeaders() });
}

// Called by app.js when another model is chosen: the capture's rounds stay drawn over its own
// models only (another model is in another frame).
function modelOfCapture(model) {
  if (!loop.shown || !view3d() || !model || capturedModels(loop.shown).includes(model.id)) return;
  view3d().showCapture($("view3d"), null);
  say("capture-message", `The 3D view shows ${model.name} now, not a model of ${loop.shown.name}: choose the ` +
    "capture again to see its rounds.");
}

async function trainCapture() {
  const info = loop.shown, token = loop.token;
  if (!info) throw new ApiError("Choose a capture first.");
  // Calibration and sigma-max-bar with section 1's calibration samples.
  const body = { downscale: Number($("train-downscale").value) || 1, warm_start: $("train-warm").checked,
    samples: Math.max(2, Number($("cal-samples").value) || 2) };
  if ($("train-iterations").value) body.iterations = Number($("train-iterations").value);
  say("capture-message", `training a model on ${info.name}...`);
  const done = await busyWhile(() => runJob("/v1/captures/" + info.id + "/train", body, $("capture-progress")));
  if (token !== loop.token) return;
  say("capture-message", `Trained round ${done.round}: test PSNR ${fmt(done.summary.test_psnr)} dB, ` +
    `sigma-max-bar ${fmt(done.summary.sigma_max_bar, 3)}, in ${done.summary.seconds.toFixed(1)} s.`);
  await loadCaptures();
  await openCapture((await apiJson("/v1/captures/" + info.id)).data, token);
}

// The next views of the capture, ranked over section 2's candidates with section 3's settings;
// the round keeps them and the 3D view draws them.
async function nextViews() {
  const info = loop.shown, token = loop.token;
  if (!info) throw new ApiError("Choose a capture first.");
  const body = Object.assign({ top_k: Math.max(1, Number($("next-count").value) || 1),
    samples: Number($("rank-samples").value), seed: Number($("rank-seed").value) }, sizeOptions("rank"), candidateBody());
  if ($("rank-strategy").value) body.strategy = $("rank-strategy").value;
  say("capture-message", `ranking the next ${plural(body.top_k, "view")} of ${info.name}...`);
  const r = await busyWhile(() => runJob("/v1/captures/" + info.id + "/next", body, $("capture-progress")));
  if (token !== loop.token) return;
  say("capture-message", `Capture next: ${plural(r.views.length, "view")} (candidates ` +
    r.views.map((v) => v.index).join(", ") + "), drawn in the 3D view.");
  await openCapture((await apiJson("/v1/captures/" + info.id)).data, token);
}

// Photos sent as a new capture, or added to the one shown as its next round (structure-from-motion
// as a job, polled); the test photos field names those held out of training.
async function sendPhotos(add) {
  const files = [...$("photos-file").files];
  if (!files.length) throw new ApiError("Choose the photos first.");
  if (add && !loop.shown) throw new ApiError("Choose the capture to add them to first.");
  const form = new FormData();
  for (const file of files) form.append("photos", file, file.name);
  const test = $("photos-test").value.split(",").map((name) => name.trim()).filter(Boolean);
  if (test.length) form.append("test", JSON.stringify(test));
  say("capture-message", `sending ${plural(files.length, "photo")}...`);
  const info = await busyWhile(() => apiJson(add ? `/v1/captures/${loop.shown.id}/photos` : "/v1/captures",
    { method: "POST", body: form }));
  $("photos-file").value = "";
  await loadCaptures();
  $("capture-select").value = info.data.id;
  await openCapture(info.data, ++loop.token);
}

// The section's buttons are off while one of its jobs runs.
async function busyWhile(action) {
  for (const id of ["capture-train", "capture-next", "photos-new", "photos-add"]) $(id).disabled = true;
  try {
    return await action();
  } finally {
    if (loop.shown) describeCapture(loop.shown);      // the buttons as the capture's state allows
  }
}

function startCaptures() {
  $("refresh-captures").addEventListener("click", () => guarded("capture-message", async () => {
    await loadCaptures();
    await captureChosen();
  }));
  $("capture-select").addEventListener("change", () => guarded("capture-message", captureChosen));
  $("capture-train").addEventListener("click", () => guarded("capture-message", trainCapture));
  $("capture-next").addEventListener("click", () => guarded("capture-message", nextViews));
  $("photos-new").addEventListener("click", () => guarded("capture-message", () => sendPhotos(false)));
  $("photos-add").addEventListener("click", () => guarded("capture-message", () => sendPhotos(true)));
}
