"use strict";
// The local pages' common pieces (rigsfm pick, rigsfm explore; served as /page.js by rigsfm/core/local_server.py,
// loaded before each page's own script): requests, SVG, and image views that zoom, pan and take clicks. Image
// coordinates are COLMAP pixels (the image spans [0, width] x [0, height]), so a CSS pixel of the unscaled image
// maps 1:1 onto them.

const SVGNS = "http://www.w3.org/2000/svg";
const $ = (id) => document.getElementById(id);

function setStatus(text, error = false) {
  const status = $("status");
  status.textContent = text;
  status.classList.toggle("error", error);
}

async function api(method, url, body) {
  const response = await fetch(url, {
    method, headers: body ? { "Content-Type": "application/json" } : {}, body: body ? JSON.stringify(body) : undefined,
  });
  const data = await response.json();
  if (!response.ok) throw new Error(data.error || response.statusText);
  return data;
}

function svgElement(name, attrs, parent) {
  const node = document.createElementNS(SVGNS, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  parent.appendChild(node);
  return node;
}

// Views keyed by k: the element "view-" + k shows "stage-" + k scaled by views[k].s and moved by (tx, ty) CSS
// pixels. imageOf(k) gives its image's { width, height }; draw(k) redraws its overlay after a change; a click
// (a press and release that did not drag) calls place(k, [x, y]) in image coordinates.
function imageViews(views, { imageOf, draw, place }) {
  function applyView(k) {
    const v = views[k];
    $("stage-" + k).style.transform = `translate(${v.tx}px, ${v.ty}px) scale(${v.s})`;
    draw(k);
  }

  function fit(k) {
    const image = imageOf(k);
    const rect = $("view-" + k).getBoundingClientRect();
    const s = Math.min(rect.width / image.width, rect.height / image.height);
    views[k] = { s, tx: (rect.width - image.width * s) / 2, ty: (rect.height - image.height * s) / 2 };
    applyView(k);
  }

  function toImage(k, clientX, clientY) {
    const rect = $("view-" + k).getBoundingClientRect();
    const v = views[k];
    return [(clientX - rect.left - v.tx) / v.s, (clientY - rect.top - v.ty) / v.s];
  }

  function toScreen(k, x, y) {
    const rect = $("view-" + k).getBoundingClientRect();
    const v = views[k];
    return [rect.left + v.tx + x * v.s, rect.top + v.ty + y * v.s];
  }

  function attach(k) {
    const view = $("view-" + k);
    let drag = null;
    view.addEventListener("wheel", (e) => {
      e.preventDefault();
      const v = views[k];
      const rect = view.getBoundingClientRect();
      const s = Math.min(64, Math.max(0.05, v.s * Math.exp(-e.deltaY * 0.0015)));
      const cx = e.clientX - rect.left, cy = e.clientY - rect.top;
      views[k] = { s, tx: cx - (cx - v.tx) * (s / v.s), ty: cy - (cy - v.ty) * (s / v.s) };
      applyView(k);
    }, { passive: false });
    view.addEventListener("mousedown", (e) => {
      if (e.button !== 0) return;
      drag = { x: e.clientX, y: e.clientY, tx: views[k].tx, ty: views[k].ty, moved: false };
    });
    window.addEventListener("mousemove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      if (Math.abs(dx) + Math.abs(dy) > 4) drag.moved = true;
      if (drag.moved) {
        views[k].tx = drag.tx + dx;
        views[k].ty = drag.ty + dy;
        applyView(k);
      }
    });
    window.addEventListener("mouseup", (e) => {
      if (!drag) return;
      const wasClick = !drag.moved;
      drag = null;
      if (wasClick) place(k, toImage(k, e.clientX, e.clientY));
    });
  }

  return { applyView, fit, toImage, toScreen, attach };
}
