// regtree results page: the tree picture, with zoom, pan, fit and clickable nodes, and the
// unattached shapes listed under it.

import { $, api, el, go, hasNumber, isAttached, isLeaf, nameOf, state } from "./core.js";

// --- the tree: zoom, pan, fit --------------------------------------------------------------
// The server draws the tree (tree.svg, matplotlib); the page shows it in a fixed-size box and
// moves a viewBox over it: zoom with the wheel, the buttons or + and −, pan by dragging or with
// the arrow keys, 0 fits the whole tree. The picture's "unattached" box is taken out of it and
// listed as buttons under the tree, so those names stay readable at any zoom.
export const TREE = {
  MAX_SCALE: 4,          // 4x the picture's natural size
  READABLE: 1,           // a found shape is shown at least at natural size (9 pt names)
  LOCATOR_BELOW: 0.75,   // under this scale a ring marks the selected shape
  PAD: 10,               // px kept free around the fitted tree
  ANIMATE_MS: 180,
};
export const tv = {
  svg: null, box: null,
  content: null,         // the tree's part of the picture, in SVG units {x, y, w, h}
  unitPx: 1,             // CSS px per SVG unit at natural size (4/3 for a picture in pt)
  boxW: 0, boxH: 0,
  view: null,            // the visible part, in SVG units; view.w / view.h == boxW / boxH
  fitted: true,          // the user has not moved the view since it was fitted
  nodes: new Map(),      // shape id -> {g, box} of each node in the tree
  frame: 0,              // pending requestAnimationFrame
  still: 0,              // timer: the view has stopped moving
  drag: null,
  justDragged: false,
  resize: null,
};
export const reducedMotion = () => window.matchMedia && matchMedia("(prefers-reduced-motion: reduce)").matches;

export async function loadTree(token) {
  const box = $("ui-tree");
  resetTreeView();
  box.replaceChildren(el("p", { class: "hint tree-message", text: "drawing the tree…" }));
  renderUnattached();
  let text;
  try {
    text = await api(`/v1/jobs/${state.job.id}/result/tree.svg`, { as: "text" });
  } catch (e) {
    if (token === state.loadToken) box.replaceChildren(el("p", { class: "error tree-message", text: `No tree: ${e.message}` }));
    return;
  }
  if (token !== state.loadToken) return;
  const started = performance.now();
  const doc = new DOMParser().parseFromString(text, "image/svg+xml");
  const svg = doc.documentElement;
  if (!svg || svg.nodeName !== "svg") {
    box.replaceChildren(el("p", { class: "error tree-message", text: "The tree picture could not be read." }));
    return;
  }
  const imported = document.importNode(svg, true);
  const vb = (imported.getAttribute("viewBox") || "").split(/[\s,]+/).map(Number);
  const widthAttr = imported.getAttribute("width") || "";
  const natural = parseFloat(widthAttr) * (/pt$/.test(widthAttr) ? 4 / 3 : 1);
  const full = vb.length === 4 && vb.every(Number.isFinite) && vb[2] > 0 && vb[3] > 0
    ? { x: vb[0], y: vb[1], w: vb[2], h: vb[3] }
    : { x: 0, y: 0, w: natural || 800, h: natural || 600 };
  const unitPx = natural > 0 ? natural / full.w : 1;
  // drawn at its natural size and moved with a CSS transform: changing the viewBox instead
  // would lay every name of the picture out again on each frame
  imported.setAttribute("width", String(full.w * unitPx));
  imported.setAttribute("height", String(full.h * unitPx));
  imported.setAttribute("viewBox", `${full.x} ${full.y} ${full.w} ${full.h}`);
  imported.setAttribute("role", "group");
  imported.setAttribute("aria-label", `registration tree of job ${state.job.id}`);
  imported.id = "ui-tree-svg";
  box.replaceChildren(imported, el("div", { id: "ui-tree-locator", class: "tree-locator", hidden: true }));
  // the unattached shapes are listed under the tree instead (readable at any zoom)
  let content = full;
  const unattachedBox = imported.querySelector("g#unattached");
  if (unattachedBox) {
    const b = unattachedBox.getBBox();
    if (b.height > 0 && b.y > full.y) content = { ...full, h: Math.max(b.y - 6 - full.y, 10) };
  }
  tv.svg = imported;
  tv.box = box;
  tv.content = content;
  tv.full = full;
  tv.unitPx = unitPx;
  makeNodesClickable(imported);
  if (unattachedBox) unattachedBox.remove();
  // a tree wider than its half of the page takes more of the page's width (before the box
  // is measured), so that it is shown larger when fitted
  const panes = box.closest(".panes");
  panes.classList.remove("big-tree");
  panes.classList.toggle("big-tree", content.w * tv.unitPx > box.clientWidth);
  sizeTreeBox();
  const first = Math.min(fitScale(), 1);
  setView(viewAt(first, content.x + content.w / 2, content.y + content.h / 2));
  tv.fitted = true;
  tv.resize = new ResizeObserver(() => {
    const w = box.clientWidth;
    if (!tv.svg || Math.abs(w - tv.boxW) < 1) return;
    const centre = viewCentre();
    const scale = scaleOf();
    sizeTreeBox();
    setView(tv.fitted ? viewAt(Math.min(fitScale(), 1), ...contentCentre()) : viewAt(scale, ...centre));
  });
  tv.resize.observe(box);
  const subject = state.route.subjectId;
  if (subject !== null && subject !== undefined) revealNode(subject, { zoom: true, animate: false });
  // the time from the picture's text to an interactive tree (for the page's own measurements)
  box.dataset.renderMs = (performance.now() - started).toFixed(1);
  box.dataset.nodes = String(tv.nodes.size);
}

export function resetTreeView() {
  if (tv.resize) tv.resize.disconnect();
  cancelAnimationFrame(tv.frame);
  Object.assign(tv, { svg: null, content: null, view: null, fitted: true, nodes: new Map(), drag: null, resize: null });
  const box = $("ui-tree");
  box.style.height = "";
  box.closest(".panes").classList.remove("big-tree");
  delete box.dataset.scale;
  delete box.dataset.view;
  delete box.dataset.renderMs;
  delete box.dataset.nodes;
  $("ui-zoom-level").textContent = "";
}

// --- unattached shapes, as buttons under the tree --------------------------------------------
export function renderUnattached() {
  const section = $("ui-unattached");
  const list = $("ui-unattached-list");
  const shapes = state.result ? state.result.subjects.filter((s) => !isAttached(s)) : [];
  section.hidden = !shapes.length;
  $("ui-unattached-count").textContent = String(shapes.length);
  list.replaceChildren(...shapes.map((s) => el("li", {},
    el("button", {
      type: "button",
      class: `chip${s.shape_id === state.selected ? " selected" : ""}`,
      "data-shape-id": String(s.shape_id),
      title: `${s.name || `shape ${s.shape_id}`} (shape ${s.shape_id})${s.reason ? `: ${s.reason}` : ""}`,
      text: s.name || `#${s.shape_id}`,
      onclick: () => openSubject(s.shape_id),
    }))));
}

export function revealChip(shapeId) {
  const chip = $("ui-unattached-list").querySelector(`button[data-shape-id="${shapeId}"]`);
  if (chip) chip.scrollIntoView({ block: "nearest", inline: "nearest" });
}

// the box: as wide as its column; as high as the tree at that width, within limits
export function sizeTreeBox() {
  const box = tv.box;
  const c = tv.content;
  tv.boxW = Math.max(box.clientWidth, 50);
  const widthScale = Math.min(1, (tv.boxW - 2 * TREE.PAD) / (c.w * tv.unitPx));
  const wanted = c.h * tv.unitPx * widthScale + 2 * TREE.PAD;
  const tallest = Math.max(360, Math.round(0.72 * window.innerHeight));
  // a tree shrunk a lot gets room to be zoomed into
  const least = widthScale < 0.6 ? 360 : 160;
  tv.boxH = Math.round(Math.min(tallest, Math.max(least, wanted)));
  box.style.height = `${tv.boxH}px`;
}

export const scaleOf = (v = tv.view) => tv.boxW / (v.w * tv.unitPx);
export const viewCentre = (v = tv.view) => [v.x + v.w / 2, v.y + v.h / 2];
export const contentCentre = () => [tv.content.x + tv.content.w / 2, tv.content.y + tv.content.h / 2];
export function fitScale() {
  const c = tv.content;
  return Math.min((tv.boxW - 2 * TREE.PAD) / (c.w * tv.unitPx), (tv.boxH - 2 * TREE.PAD) / (c.h * tv.unitPx));
}
export const minScale = () => Math.min(0.8 * fitScale(), 1);
export const clampScale = (s) => Math.min(TREE.MAX_SCALE, Math.max(minScale(), s));
export function viewAt(scale, cx, cy) {
  const s = clampScale(scale);
  const w = tv.boxW / (s * tv.unitPx);
  const h = tv.boxH / (s * tv.unitPx);
  return { x: cx - w / 2, y: cy - h / 2, w, h };
}
// keep the view's centre over the tree, so it cannot be lost by panning
export function clampView(v) {
  const c = tv.content;
  const [cx, cy] = viewCentre(v);
  const x = Math.min(c.x + c.w, Math.max(c.x, cx));
  const y = Math.min(c.y + c.h, Math.max(c.y, cy));
  return { ...v, x: v.x + (x - cx), y: v.y + (y - cy) };
}

export function setView(v) {
  if (!tv.svg) return;
  tv.view = clampView(v);
  const { x, y, w, h } = tv.view;
  const scale = scaleOf();
  const k = scale * tv.unitPx;
  moving();
  tv.svg.style.transform = `translate(${-(x - tv.full.x) * k}px, ${-(y - tv.full.y) * k}px) scale(${scale})`;
  tv.box.dataset.scale = scale.toFixed(4);
  tv.box.dataset.view = [x, y, w, h].map((n) => n.toFixed(1)).join(" ");  // in the picture's units
  $("ui-zoom-level").textContent = `${Math.round(scale * 100)}%`;
  $("ui-zoom-in").disabled = scale >= TREE.MAX_SCALE - 1e-6;
  $("ui-zoom-out").disabled = scale <= minScale() + 1e-6;
  placeLocator();
}

// mark the box as moving until the view has stood still for a moment
export function moving() {
  if (!tv.box) return;
  tv.box.classList.add("moving");
  clearTimeout(tv.still);
  tv.still = setTimeout(() => tv.box && tv.box.classList.remove("moving"), 200);
}

// move to a view, in a few frames unless the user prefers no motion
export function moveTo(target, animate = true) {
  cancelAnimationFrame(tv.frame);
  if (!animate || reducedMotion() || !tv.view) { setView(target); return; }
  const from = tv.view;
  const t0 = performance.now();
  const step = (now) => {
    const t = Math.min(1, (now - t0) / TREE.ANIMATE_MS);
    const k = t * (2 - t);
    // interpolate the centre and the scale (not the corners): zooming looks steady
    const [fx, fy] = viewCentre(from);
    const [tx, ty] = viewCentre(target);
    const s = Math.exp(Math.log(scaleOf(from)) + k * (Math.log(scaleOf(target)) - Math.log(scaleOf(from))));
    const w = tv.boxW / (s * tv.unitPx);
    const h = tv.boxH / (s * tv.unitPx);
    setView({ x: fx + k * (tx - fx) - w / 2, y: fy + k * (ty - fy) - h / 2, w, h });
    if (t < 1) tv.frame = requestAnimationFrame(step);
  };
  tv.frame = requestAnimationFrame(step);
}

// zoom by `factor` about a point of the box (CSS px from its top left; default its centre)
export function zoomBy(factor, px = tv.boxW / 2, py = tv.boxH / 2, animate = false) {
  if (!tv.view) return;
  const v = tv.view;
  const ux = v.x + (px / tv.boxW) * v.w;
  const uy = v.y + (py / tv.boxH) * v.h;
  const s = clampScale(scaleOf() * factor);
  const w = tv.boxW / (s * tv.unitPx);
  const h = tv.boxH / (s * tv.unitPx);
  tv.fitted = false;
  moveTo({ x: ux - (px / tv.boxW) * w, y: uy - (py / tv.boxH) * h, w, h }, animate);
}
export function zoomFit(animate = true) {
  if (!tv.view) return;
  tv.fitted = true;
  moveTo(viewAt(fitScale(), ...contentCentre()), animate);
}
export function zoomActual() {
  if (!tv.view) return;
  tv.fitted = false;
  const sel = state.selected !== null ? tv.nodes.get(state.selected) : null;
  moveTo(viewAt(1, ...(sel ? nodeCentre(sel.box) : viewCentre())));
}
export function panBy(dxPx, dyPx) {
  if (!tv.view) return;
  const k = tv.view.w / tv.boxW;
  tv.fitted = false;
  setView({ ...tv.view, x: tv.view.x + dxPx * k, y: tv.view.y + dyPx * k });
}

export const nodeCentre = (b) => [b.x + b.width / 2, b.y + b.height / 2];

// bring a node into view: centred when outside it; with zoom, at a readable scale at least
export function revealNode(shapeId, { zoom = false, animate = true } = {}) {
  const node = tv.nodes.get(shapeId);
  if (!node || !tv.view) return;
  const b = node.box;
  const v = tv.view;
  const scale = scaleOf();
  if (zoom && scale < TREE.READABLE) {
    tv.fitted = false;
    moveTo(viewAt(TREE.READABLE, ...nodeCentre(b)), animate);
  } else {
    const m = Math.min(v.w, v.h) * 0.04;
    const inside = b.x >= v.x + m && b.x + b.width <= v.x + v.w - m && b.y >= v.y + m && b.y + b.height <= v.y + v.h - m;
    if (!inside) {
      tv.fitted = false;
      moveTo(viewAt(scale, ...nodeCentre(b)), animate);
    }
  }
  if (zoom) flash(node.g);
}

export function flash(g) {
  g.classList.remove("rt-flash");
  void g.getBoundingClientRect(); // a style and layout pass in between restarts the animation
  g.classList.add("rt-flash");
  setTimeout(() => g.classList.remove("rt-flash"), 1600);
}

// a ring over the selected shape when the tree is drawn too small to see its highlight
export function placeLocator() {
  const ring = $("ui-tree-locator");
  if (!ring) return;
  const node = state.selected !== null ? tv.nodes.get(state.selected) : null;
  if (!node || scaleOf() >= TREE.LOCATOR_BELOW) { ring.hidden = true; return; }
  const b = node.box;
  const v = tv.view;
  // the shape's marker sits at the top of its name (at the bottom for the model's)
  const isModel = state.result && state.selected === state.result.root_shape_id;
  const ux = b.width > b.height ? b.x + b.width / 2 : b.x + Math.min(b.width, 8) / 2;
  const uy = isModel ? b.y + b.height : b.y;
  const px = ((ux - v.x) / v.w) * tv.boxW;
  const py = ((uy - v.y) / v.h) * tv.boxH;
  ring.hidden = px < -20 || py < -20 || px > tv.boxW + 20 || py > tv.boxH + 20;
  ring.style.left = `${px}px`;
  ring.style.top = `${py}px`;
}

// Each node gets a hit area over its name and its marker (above the name; below it for the
// model, whose name is on top), a tooltip and button semantics. All sizes are read first and
// the DOM written after: interleaving getBBox with writes would lay the picture out again
// for every node.
export function makeNodesClickable(svg) {
  const ns = "http://www.w3.org/2000/svg";
  const rootId = state.result.root_shape_id;
  tv.nodes = new Map();
  const found = [];
  for (const g of svg.querySelectorAll("g[id^='node-']")) {
    const m = /^node-(\d+)$/.exec(g.id);
    if (m) found.push({ g, shapeId: Number(m[1]), box: g.getBBox() });
  }
  for (const { g, shapeId, box } of found) {
    const up = shapeId === rootId ? 3 : 11;
    const down = shapeId === rootId ? 11 : 3;
    const area = { x: box.x - 3, y: box.y - up, width: box.width + 6, height: box.height + up + down };
    const subject = state.subjectsById.get(shapeId);
    g.classList.add("rt-node");
    if (subject && isLeaf(subject)) g.classList.add("rt-leaf");
    g.setAttribute("data-shape-id", String(shapeId));
    g.setAttribute("tabindex", "0");
    g.setAttribute("role", "button");
    g.setAttribute("aria-label", `shape ${nameOf(shapeId)}`);
    const hit = document.createElementNS(ns, "rect");
    hit.setAttribute("x", String(area.x));
    hit.setAttribute("y", String(area.y));
    hit.setAttribute("width", String(area.width));
    hit.setAttribute("height", String(area.height));
    hit.setAttribute("rx", "3");
    hit.setAttribute("class", "rt-hit");
    g.insertBefore(hit, g.firstChild);
    const title = document.createElementNS(ns, "title");
    title.textContent = `${nameOf(shapeId)} (shape ${shapeId})`
      + (subject && isLeaf(subject) ? ", low-confidence leaf" : "")
      + (subject && hasNumber(subject.confidence) ? `, confidence ${subject.confidence.toFixed(2)}` : "");
    g.append(title);
    tv.nodes.set(shapeId, { g, box: area });
  }
}

export function openFromTree(shapeId) {
  state.fromTree = true;
  openSubject(shapeId);
}

// open a subject (route), or only bring it into view when it is open already
export function openSubject(shapeId, { zoom = false } = {}) {
  if (!state.job) return;
  const hash = `#/jobs/${state.job.id}/subjects/${shapeId}`;
  if (location.hash === hash) {
    revealNode(shapeId, { zoom });
    revealChip(shapeId);
    return;
  }
  go(hash);  // selectSubject brings it into view, zoomed in
}

export function setupTreeView() {
  const box = $("ui-tree");
  box.addEventListener("click", (event) => {
    if (tv.justDragged) { event.stopPropagation(); event.preventDefault(); return; }
    const g = event.target.closest && event.target.closest("g.rt-node");
    if (g) openFromTree(Number(g.dataset.shapeId));
  }, true);
  box.addEventListener("wheel", (event) => {
    if (!tv.view) return;
    event.preventDefault();
    const r = box.getBoundingClientRect();
    const unit = event.deltaMode === 1 ? 16 : event.deltaMode === 2 ? r.height : 1;
    if (event.shiftKey && !event.ctrlKey) { panBy(event.deltaY * unit, 0); return; }
    if (Math.abs(event.deltaX) > Math.abs(event.deltaY)) { panBy(event.deltaX * unit, 0); return; }
    // ctrl + wheel is a trackpad pinch: finer steps
    const k = event.ctrlKey ? 0.01 : 0.0015;
    zoomBy(Math.exp(-event.deltaY * unit * k), event.clientX - r.left, event.clientY - r.top);
  }, { passive: false });
  box.addEventListener("pointerdown", (event) => {
    if (!tv.view || event.button !== 0) return;
    tv.drag = { id: event.pointerId, x: event.clientX, y: event.clientY, moved: false };
    tv.justDragged = false;
  });
  box.addEventListener("pointermove", (event) => {
    const d = tv.drag;
    if (!d || d.id !== event.pointerId) return;
    const dx = event.clientX - d.x;
    const dy = event.clientY - d.y;
    if (!d.moved && Math.hypot(dx, dy) < 4) return;
    if (!d.moved) {
      d.moved = true;
      box.setPointerCapture(event.pointerId);
      box.classList.add("panning");
    }
    d.x = event.clientX;
    d.y = event.clientY;
    cancelAnimationFrame(tv.frame);
    panBy(-dx, -dy);
  });
  const endDrag = (event) => {
    const d = tv.drag;
    if (!d || d.id !== event.pointerId) return;
    tv.drag = null;
    box.classList.remove("panning");
    if (d.moved) {
      tv.justDragged = true;  // the click that ends a drag opens nothing
      setTimeout(() => { tv.justDragged = false; }, 0);
    }
  };
  box.addEventListener("pointerup", endDrag);
  box.addEventListener("pointercancel", endDrag);
  box.addEventListener("keydown", (event) => {
    if (!tv.view || event.altKey || event.ctrlKey || event.metaKey) return;
    const g = event.target.closest && event.target.closest("g.rt-node");
    const step = 0.15 * Math.min(tv.boxW, tv.boxH);
    const keys = {
      "+": () => zoomBy(1.4, undefined, undefined, true),
      "=": () => zoomBy(1.4, undefined, undefined, true),
      "-": () => zoomBy(1 / 1.4, undefined, undefined, true),
      "_": () => zoomBy(1 / 1.4, undefined, undefined, true),
      "0": () => zoomFit(),
      "1": () => zoomActual(),
      ArrowLeft: () => panBy(-step, 0),
      ArrowRight: () => panBy(step, 0),
      ArrowUp: () => panBy(0, -step),
      ArrowDown: () => panBy(0, step),
    };
    if (g && (event.key === "Enter" || event.key === " ")) {
      event.preventDefault();
      openFromTree(Number(g.dataset.shapeId));
    } else if (keys[event.key]) {
      event.preventDefault();
      keys[event.key]();
    }
  });
  // the picture overflows the box (which never scrolls: the transform moves it), but the
  // browser scrolls the box to show an element that gets focus; undo that
  box.addEventListener("scroll", () => { box.scrollTop = 0; box.scrollLeft = 0; });
  // a shape reached with Tab is brought into view
  box.addEventListener("focusin", (event) => {
    const g = event.target.closest && event.target.closest("g.rt-node");
    if (g) revealNode(Number(g.dataset.shapeId));
  });
  $("ui-zoom-in").addEventListener("click", () => zoomBy(1.4, undefined, undefined, true));
  $("ui-zoom-out").addEventListener("click", () => zoomBy(1 / 1.4, undefined, undefined, true));
  $("ui-zoom-fit").addEventListener("click", () => zoomFit());
  $("ui-zoom-actual").addEventListener("click", () => zoomActual());
}
