"use strict";
// rigsfm pick: two wide images, click pairs, epipolar line of the point being placed (from 8 pairs on).
// The views, requests and SVG helpers are page.js's; image coordinates are COLMAP pixels.

const SIDES = ["a", "b"];
const state = { images: [], pairs: [], pending: null, selected: -1, model: false, epi: null, info: {} };
const views = { a: { s: 1, tx: 0, ty: 0 }, b: { s: 1, tx: 0, ty: 0 } };
const { fit, toImage, toScreen, attach } = imageViews(views, {
  imageOf: (side) => state.images[side === "a" ? 0 : 1], draw, place,
});

function pendingKey() { return "rigsfm-pick:" + state.images.map((i) => i.name).join("|"); }
function storePending() {
  if (state.pending) localStorage.setItem(pendingKey(), JSON.stringify(state.pending));
  else localStorage.removeItem(pendingKey());
}

function draw(side) {
  const svg = $("svg-" + side);
  const image = state.images[side === "a" ? 0 : 1];
  if (!image) return;
  svg.setAttribute("width", image.width);
  svg.setAttribute("height", image.height);
  svg.setAttribute("viewBox", `0 0 ${image.width} ${image.height}`);
  svg.replaceChildren();
  const r = 7 / views[side].s;
  if (state.epi && state.epi.side === side && state.epi.polyline && state.epi.polyline.length > 1) {
    svgElement("polyline", { class: "epipolar", id: "epipolar-" + side,
      points: state.epi.polyline.map((p) => p.join(",")).join(" ") }, svg);
  }
  state.pairs.forEach((pair, i) => {
    const [x, y] = pair[side];
    const cls = (pair.flagged ? " flagged" : "") + (i === state.selected ? " selected" : "");
    svgElement("circle", { class: "marker" + cls, cx: x, cy: y, r, "data-index": i }, svg);
    const label = svgElement("text", { class: cls, x: x + r, y: y - r, "font-size": 12 / views[side].s }, svg);
    label.textContent = String(i + 1);
  });
  if (state.pending && state.pending.side === side) {
    const [x, y] = state.pending.xy;
    svgElement("circle", { class: "marker pending", id: "pending", cx: x, cy: y, r: 1.4 * r }, svg);
  }
}

function drawTable() {
  const body = $("pairs").querySelector("tbody");
  body.replaceChildren();
  state.pairs.forEach((pair, i) => {
    const row = document.createElement("tr");
    row.className = (pair.flagged ? "flagged " : "") + (i === state.selected ? "selected" : "");
    const cells = [i + 1, ...pair.a.map((v) => v.toFixed(2)), ...pair.b.map((v) => v.toFixed(2)),
      pair.distance_px === null ? "-" : pair.distance_px.toFixed(2)];
    for (const value of cells) {
      const td = document.createElement("td");
      td.textContent = value;
      row.appendChild(td);
    }
    const td = document.createElement("td");
    const remove = document.createElement("button");
    remove.textContent = "×";
    remove.title = "delete this pair";
    remove.addEventListener("click", (e) => { e.stopPropagation(); removePair(i); });
    td.appendChild(remove);
    row.appendChild(td);
    row.addEventListener("click", () => { state.selected = i === state.selected ? -1 : i; redraw(); });
    body.appendChild(row);
  });
}

function describe() {
  const n = state.pairs.length;
  const flagged = state.pairs.filter((p) => p.flagged).length;
  const need = state.info.min_pairs - n;
  const model = state.model
    ? `epipolar lines from ${n} pairs (${state.info.calibrated ? "calibrated E" : "fundamental matrix"})`
    : `epipolar lines from ${state.info.min_pairs} pairs on (${need} more)`;
  const next = state.pending ? `; now click the partner in image ${state.pending.side === "a" ? "b" : "a"}` : "";
  setStatus(`${n} pairs saved to ${state.info.csv}; ${model}; ${flagged} flagged (> ${state.info.flag_px} px)${next}`);
}

function redraw() { SIDES.forEach(draw); drawTable(); describe(); }

function applyState(data) {
  state.info = data;
  state.revision = data.revision;
  state.images = data.images;
  state.pairs = data.pairs;
  state.model = data.model;
  if (state.selected >= state.pairs.length) state.selected = -1;
}

async function updateEpipolar() {
  state.epi = null;
  const pending = state.pending;
  if (pending && state.model) {
    const [x, y] = pending.xy;
    const data = await api("GET", `/api/epipolar?side=${pending.side}&x=${x}&y=${y}`);
    if (pending !== state.pending) return;  // the point moved on while the line was computed
    state.epi = { side: pending.side === "a" ? "b" : "a", polyline: data.polyline };
  }
  redraw();
}

// Saves go to the server one at a time, each with the newest pairs. A response is applied only when no
// change came after its request: an older response must not replace newer clicks (fast clicking on a slow
// server lost pairs that way), and an older request must not overwrite a newer CSV.
// Another tab or script may have saved meanwhile: the server applies this page's edit on top of the newer pairs
// (by the revision sent), and newer clicks here are redone on top of what it saved (rebase).
function pairKey(p) { return [...p.a, ...p.b].map((v) => v.toFixed(3)).join(","); }
function rebase(saved, base, now) {
  const same = (x, y) => x.length === y.length && x.every((p, i) => pairKey(p) === pairKey(y[i]));
  if (same(saved, base)) return now;
  const before = new Set(base.map(pairKey)), after = new Set(now.map(pairKey));
  const kept = saved.filter((p) => !(before.has(pairKey(p)) && !after.has(pairKey(p))));
  const have = new Set(kept.map(pairKey));
  return kept.concat(now.filter((p) => !before.has(pairKey(p)) && !have.has(pairKey(p))));
}

let saveQueue = Promise.resolve();
let changes = 0;
function save() {
  const change = ++changes;
  redraw();  // the change shows at once; the server's distances and flags follow
  saveQueue = saveQueue.then(async () => {
    if (change !== changes) return;  // a later save sends these pairs too
    try {
      const sent = state.pairs.slice();
      const data = await api("PUT", "/api/pairs", {
        pairs: sent.map((p) => [...p.a, ...p.b]), revision: state.revision,
      });
      state.revision = data.revision;  // the next save starts from this one
      if (change !== changes) {  // newer clicks came meanwhile: they are redone on what the server saved
        state.pairs = rebase(data.pairs, sent, state.pairs);
        return;
      }
      applyState(data);
      await updateEpipolar();
    } catch (error) {
      setStatus("NOT SAVED: " + error.message, true);
    }
  });
  return saveQueue;
}

async function place(side, xy) {
  const image = state.images[side === "a" ? 0 : 1];
  if (xy[0] < 0 || xy[1] < 0 || xy[0] > image.width || xy[1] > image.height) return;
  if (state.pending && state.pending.side !== side) {
    const pair = side === "b" ? { a: state.pending.xy, b: xy } : { a: xy, b: state.pending.xy };
    state.pairs.push({ ...pair, distance_px: null, flagged: false });
    state.pending = null;
    state.epi = null;
    storePending();
    await save();
  } else {
    state.pending = { side, xy };
    storePending();
    await updateEpipolar();
  }
}

async function undo() {
  if (state.pending) {
    state.pending = null;
    storePending();
    await updateEpipolar();
  } else if (state.pairs.length) {
    state.pairs.pop();
    await save();
  }
}

async function removePair(i) {
  state.pairs.splice(i, 1);
  state.selected = -1;
  await save();
}

async function reload() {
  try {
    applyState(await api("GET", "/api/state?reload=1"));
  } catch (error) {
    setStatus("cannot load: " + error.message, true);
    return;
  }
  const stored = localStorage.getItem(pendingKey());
  state.pending = stored ? JSON.parse(stored) : null;
  SIDES.forEach((side, k) => {
    $("title-" + side).textContent = `${side}: ${state.images[k].name} (${state.images[k].width}x${state.images[k].height})`;
    const img = $("img-" + side);
    img.style.width = state.images[k].width + "px";
    img.style.height = state.images[k].height + "px";
  });
  SIDES.forEach(fit);
  await updateEpipolar();
}

SIDES.forEach(attach);
$("undo").addEventListener("click", undo);
$("cancel").addEventListener("click", () => { state.pending = null; storePending(); updateEpipolar(); });
$("save").addEventListener("click", save);
$("reload").addEventListener("click", reload);
$("fit").addEventListener("click", () => SIDES.forEach(fit));
window.addEventListener("keydown", (e) => {
  if ((e.ctrlKey || e.metaKey) && e.key === "z") { e.preventDefault(); undo(); }
  if (e.key === "Escape") { state.pending = null; storePending(); updateEpipolar(); }
});
window.addEventListener("resize", () => SIDES.forEach(fit));

window.picker = { state, views, toScreen, toImage, ready: reload(), saved: () => saveQueue };
