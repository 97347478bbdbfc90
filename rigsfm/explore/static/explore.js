"use strict";
// rigsfm explore: the narrow images of one frame; a click shows its band in the other views and its ray on the
// floor; clicks of one person in several views are triangulated and saved. The views (zoom, pan, click),
// requests and SVG helpers are page.js's; image coordinates are COLMAP pixels.

const state = { info: {}, frame: null, views: [], persons: [], current: null, bands: null };
const views = [];  // per view: { s, tx, ty }
const { fit, toImage, toScreen, attach } = imageViews(views, {
  imageOf: (k) => state.views[k], draw, place,
});

const person = (label) => state.persons.find((p) => p.person === label);
const q = () => "frame=" + encodeURIComponent(state.frame);

// ---- views ---------------------------------------------------------------------------------------------------

function buildViews() {
  const root = $("views");
  root.replaceChildren();
  state.views.forEach((image, k) => {
    const panel = document.createElement("section");
    panel.className = "panel";
    panel.innerHTML = `<div class="title" id="title-${k}"></div><div class="viewport" id="view-${k}">` +
      `<div class="stage" id="stage-${k}"><img id="img-${k}" draggable="false" alt="view ${k}">` +
      `<svg id="svg-${k}" xmlns="${SVGNS}"></svg></div></div>`;
    root.appendChild(panel);
    $("title-" + k).textContent = `${k + 1}: ${image.name} (${image.width}x${image.height})`;
    const img = $("img-" + k);
    img.style.width = image.width + "px";
    img.style.height = image.height + "px";
    img.src = `/image?${q()}&view=${k}`;
    views[k] = { s: 1, tx: 0, ty: 0 };
    attach(k);
  });
  views.length = state.views.length;
}

// ---- drawing --------------------------------------------------------------------------------------------------

function draw(k) {
  const svg = $("svg-" + k);
  const image = state.views[k];
  if (!svg || !image) return;
  svg.setAttribute("width", image.width);
  svg.setAttribute("height", image.height);
  svg.setAttribute("viewBox", `0 0 ${image.width} ${image.height}`);
  svg.replaceChildren();
  const scale = views[k].s;
  const band = state.bands && state.bands.bands.find((b) => b.view === k);
  if (band && band.polyline.length > 1) {
    const points = band.polyline.map((p) => p.join(",")).join(" ");
    if (band.band_px) {  // a stroke of the band's full width: every point within band_px of the curve
      svgElement("polyline", { class: "band", id: "band-" + k, points, "stroke-width": 2 * band.band_px }, svg);
    }
    svgElement("polyline", { class: "centre", id: "centre-" + k, points }, svg);
    for (const tick of band.ticks) {
      svgElement("circle", { class: "tick", cx: tick.xy[0], cy: tick.xy[1], r: 3 / scale }, svg);
      const text = svgElement("text", { x: tick.xy[0] + 5 / scale, y: tick.xy[1] - 4 / scale,
        "font-size": 11 / scale }, svg);
      text.textContent = `${tick.height} m`;
    }
  }
  const r = 7 / scale;
  for (const p of state.persons) {
    p.clicks.forEach((click, n) => {
      if (click.view !== k) return;
      const outside = click.outside === true;  // beyond the band + the two clicks' noise (session.py)
      const cls = "marker" + (p.person === state.current ? " current" : "") + (n === 0 ? " anchor" : "")
        + (outside ? " outside" : "");
      svgElement("circle", { class: cls, cx: click.xy[0], cy: click.xy[1], r, "data-person": p.person }, svg);
      const text = svgElement("text", { x: click.xy[0] + r, y: click.xy[1] - r, "font-size": 12 / scale }, svg);
      text.textContent = p.person;
    });
  }
}

function drawFloor() {
  const svg = $("floor");
  svg.replaceChildren();
  const cams = (state.info.floor_map || {}).cameras || [];
  const xs = [], ys = [];
  for (const c of cams) {
    xs.push(c.centre[0]); ys.push(c.centre[1]);
    for (const p of c.footprint || []) { xs.push(p[0]); ys.push(p[1]); }
  }
  if (!xs.length) return;
  const pad = 1;
  const x0 = Math.floor(Math.min(...xs) - pad), x1 = Math.ceil(Math.max(...xs) + pad);
  const y0 = Math.floor(Math.min(...ys) - pad), y1 = Math.ceil(Math.max(...ys) + pad);
  svg.setAttribute("viewBox", `${x0} ${-y1} ${x1 - x0} ${y1 - y0}`);  // world y up: drawn with -y
  const g = svgElement("g", { transform: "scale(1,-1)" }, svg);
  for (let x = x0; x <= x1; x++) svgElement("line", { class: "grid", x1: x, y1: y0, x2: x, y2: y1 }, g);
  for (let y = y0; y <= y1; y++) svgElement("line", { class: "grid", x1: x0, y1: y, x2: x1, y2: y }, g);
  for (const c of cams) {
    if (c.footprint) {
      svgElement("polygon", { class: "footprint", points: c.footprint.map((p) => p.join(",")).join(" ") }, g);
    }
    svgElement("circle", { class: "camera", cx: c.centre[0], cy: c.centre[1], r: 0.25 }, g);
    const t = svgElement("text", { x: c.centre[0] + 0.3, y: -c.centre[1], "font-size": 0.7,
      transform: "scale(1,-1)" }, g);
    t.textContent = String(c.view + 1);
  }
  const trace = state.bands && state.bands.floor;
  if (trace && trace.segment.length === 2) {
    const [a, b] = trace.segment;
    svgElement("line", { class: "trace", id: "trace", x1: a[0], y1: a[1], x2: b[0], y2: b[1] }, g);
    for (const tick of trace.ticks) svgElement("circle", { class: "tick", cx: tick.xy[0], cy: tick.xy[1], r: 0.12 }, g);
  }
  for (const p of state.persons) {
    if (!p.point) continue;
    const [x, y] = p.point.xyz;
    const e = p.point.floor_ellipse_95;
    svgElement("ellipse", { class: "ellipse", id: "ellipse-" + p.person, cx: x, cy: y,
      rx: Math.max(e.semi_axes_m[0], 0.01), ry: Math.max(e.semi_axes_m[1], 0.01),
      transform: `rotate(${e.angle_deg} ${x} ${y})` }, g);
    svgElement("circle", { class: "point" + (p.person === state.current ? " current" : ""), cx: x, cy: y, r: 0.08 }, g);
    const t = svgElement("text", { x: x + 0.2, y: -y, "font-size": 0.6, transform: "scale(1,-1)" }, g);
    t.textContent = p.person;
  }
}

function drawTable() {
  const body = $("persons").querySelector("tbody");
  body.replaceChildren();
  for (const p of state.persons) {
    const row = document.createElement("tr");
    row.className = p.person === state.current ? "current" : "";
    row.dataset.person = p.person;
    const pt = p.point;
    const distances = p.clicks.slice(1).map((c) => c.distance_px === null || c.distance_px === undefined
      ? `${c.view + 1}: no band`
      : `${c.view + 1}: ${c.distance_px.toFixed(1)} px (${c.band_units === null ? "-" : c.band_units.toFixed(2)})`);
    const cells = [p.person, p.clicks.map((c) => c.view + 1).join(","),
      pt ? pt.xyz[0].toFixed(3) : "-", pt ? pt.xyz[1].toFixed(3) : "-",
      pt ? `${pt.xyz[2].toFixed(3)} ± ${pt.height_sigma_m.toFixed(3)}` : "-",
      pt ? pt.floor_ellipse_95.semi_axes_m.map((v) => v.toFixed(3)).join(" × ") : "-",
      distances.join("; ") || "-"];
    cells.forEach((value, n) => {
      const td = document.createElement("td");
      td.textContent = value;
      if (n === 6 && p.clicks.some((c) => c.outside === true)) td.className = "outside";
      row.appendChild(td);
    });
    const td = document.createElement("td");
    const remove = document.createElement("button");
    remove.textContent = "×";
    remove.title = "delete this person";
    remove.addEventListener("click", (e) => { e.stopPropagation(); removePerson(p.person); });
    td.appendChild(remove);
    row.appendChild(td);
    row.addEventListener("click", () => select(p.person === state.current ? null : p.person));
    body.appendChild(row);
  }
}

function describe() {
  const plural = (count, word) => `${count} ${word}${count === 1 ? "" : "s"}`;
  const info = state.info;
  const n = state.persons.reduce((sum, p) => sum + p.clicks.length, 0);
  const foreign = info.foreign_rows ? `; ${plural(info.foreign_rows, "foreign row")} kept as they are` : "";
  const elsewhere = info.labels_elsewhere ? `; ${plural(info.labels_elsewhere, "label")} in other frames` : "";
  const stale = info.stale_labels ? `; ${plural(info.stale_labels, "label")} clicked on other pictures of the same `
    + "names set aside (kept in a backup at the next save)" : "";
  const next = state.current ? `; ${state.current}: click them in another view, or Next person` : "; click a person";
  setStatus(`${plural(n, "label")} of ${plural(state.persons.length, "person")} saved to ${info.csv}${elsewhere}`
    + `${foreign}${stale}${next}`);
  $("note").textContent = `Band: the anchor's (first click's) epipolar curve between heights ${info.heights[0]} and ` +
    `${info.heights[1]} m (ticks at ${info.ticks.join(", ")} m), widened by the pair's calibrated 95 % band; ` +
    `a click is outside beyond the band + ${info.click_allowance_px} px (the two clicks' noise). ` +
    "Triangulation: linear, then least squares on the pixels; its uncertainty from click noise " +
    `±${info.click_sigma_px} px` + (info.pose_uncertainty
      ? " plus each camera's pose 1-sigma (summary.json: centre, rotation), cameras taken as independent."
      : " only (this result reports no pose uncertainty).");
}

function redraw() { state.views.forEach((_, k) => draw(k)); drawFloor(); drawTable(); describe(); }

// ---- labels ---------------------------------------------------------------------------------------------------

function applyState(data) {
  state.info = data;
  state.persons = data.persons;
  if (state.current && !person(state.current)) state.current = null;
}

async function updateBands() {
  const p = state.current && person(state.current);
  if (!p || !p.clicks.length) { state.bands = null; redraw(); return; }
  const anchor = p.clicks[0];
  const data = await api("GET", `/api/band?${q()}&view=${anchor.view}&x=${anchor.xy[0]}&y=${anchor.xy[1]}`);
  const now = state.current && person(state.current);
  // the anchor moved on while the bands were computed
  if (!now || now.clicks[0].view !== anchor.view || String(now.clicks[0].xy) !== String(anchor.xy)) return;
  state.bands = data;
  redraw();
}

// Saves go one at a time, each with the newest labels; a response is applied only when no change came after its
// request (as in rigsfm pick: an older answer must not replace newer clicks).
let saveQueue = Promise.resolve();
let changes = 0;
function save() {
  const change = ++changes;
  redraw();
  saveQueue = saveQueue.then(async () => {
    if (change !== changes) return;
    const labels = [];
    for (const p of state.persons) for (const c of p.clicks) {
      labels.push({ image: state.views[c.view].name, x: c.xy[0], y: c.xy[1], person: p.person });
    }
    try {
      const data = await api("PUT", "/api/labels", { frame: state.frame, labels });
      if (change !== changes) return;
      applyState(data);
      if (data.backup) setStatus(`the CSV as it was is kept in ${data.backup}`);
      await updateBands();
    } catch (error) {
      setStatus("NOT SAVED: " + error.message, true);
    }
  });
  return saveQueue;
}

function newLabel() {
  let n = 0;
  for (const p of state.persons) {
    const m = /^p(\d+)$/.exec(p.person);
    if (m) n = Math.max(n, Number(m[1]));
  }
  return "p" + (n + 1);
}

async function place(k, xy) {
  const image = state.views[k];
  if (xy[0] < 0 || xy[1] < 0 || xy[0] > image.width || xy[1] > image.height) return;
  let p = state.current && person(state.current);
  if (!p) {
    p = { person: newLabel(), clicks: [], point: null };
    state.persons.push(p);
    state.current = p.person;
  }
  const existing = p.clicks.find((c) => c.view === k);
  if (existing) { existing.xy = xy; delete existing.band_units; } else p.clicks.push({ view: k, xy });
  if (p.clicks[0].view === k) state.bands = null;
  await save();
}

async function select(label) {
  state.current = label;
  await updateBands();
}

async function undo() {
  const p = state.current && person(state.current);
  if (!p) return;
  p.clicks.pop();
  if (!p.clicks.length) {
    state.persons = state.persons.filter((x) => x !== p);
    state.current = null;
    state.bands = null;
  }
  await save();
}

async function removePerson(label) {
  state.persons = state.persons.filter((p) => p.person !== label);
  if (state.current === label) { state.current = null; state.bands = null; }
  await save();
}

async function load(frame, reload) {
  try {
    const url = "/api/state?" + (frame ? "frame=" + encodeURIComponent(frame) : "") + (reload ? "&reload=1" : "");
    const data = await api("GET", url);
    const changed = data.frame !== state.frame;
    state.frame = data.frame;
    state.views = data.views;
    state.current = null;
    state.bands = null;
    applyState(data);
    const select = $("frame");
    select.replaceChildren(...data.frames.map((f) => {
      const option = document.createElement("option");
      option.value = option.textContent = f;
      return option;
    }));
    select.value = data.frame;
    if (changed || !views.length) buildViews();
    state.views.forEach((_, k) => fit(k));
    redraw();
  } catch (error) {
    setStatus("cannot load: " + error.message, true);
  }
}

$("frame").addEventListener("change", (e) => load(e.target.value, false));
$("next").addEventListener("click", () => select(null));
$("undo").addEventListener("click", undo);
$("reload").addEventListener("click", () => load(state.frame, true));
$("fit").addEventListener("click", () => state.views.forEach((_, k) => fit(k)));
window.addEventListener("keydown", (e) => {
  if ((e.ctrlKey || e.metaKey) && e.key === "z") { e.preventDefault(); undo(); }
  if (e.key === "n" || e.key === "Escape") select(null);
});
window.addEventListener("resize", () => state.views.forEach((_, k) => fit(k)));

const initial = new URLSearchParams(location.search).get("frame");
window.explore = { state, views, toScreen, toImage, ready: load(initial, false), saved: () => saveQueue, select };
