// regtree results page: the subjects table and one subject's panel.

import { $, api, el, fmtNum, go, hasNumber, isAttached, isLeaf, nameOf, notice, showBlob, state } from "./core.js";
import { placeLocator, revealChip, revealNode, tv } from "./tree.js";

// --- a subject's status ---------------------------------------------------------------------
export const STATUS = { tree: "tree member", leaf: "low-confidence leaf", unattached: "unattached" };
export const statusOf = (s) => s.status; // the server states it: tree, leaf or unattached
export const statusBadgeOf = (s) => {
  const status = statusOf(s);
  return el("span", { class: `badge ${status}`, "data-status": status, text: STATUS[status] });
};

// --- subjects table -------------------------------------------------------------------------
export function sortValue(s, key) {
  if (key === "parent") return s.parent_shape_id === null || s.parent_shape_id === undefined ? "" : nameOf(s.parent_shape_id);
  if (key === "status") return ["tree", "leaf", "unattached"].indexOf(statusOf(s));
  const v = s[key];
  return v === null || v === undefined ? null : v;
}

// the subjects the table's filter lets through
export function shownSubjects() {
  const { show, minConfidence } = state.filter;
  return state.result.subjects.filter((s) => (show === "all" || statusOf(s) === show)
    && (minConfidence === null || (hasNumber(s.confidence) && s.confidence >= minConfidence)));
}

export function renderTable() {
  const { key, dir } = state.sort;
  const shown = shownSubjects();
  const total = state.result.subjects.length;
  $("ui-subjects-count").textContent = shown.length === total ? `${total} subjects` : `${shown.length} of ${total} subjects`;
  const rows = shown.sort((a, b) => {
    const va = sortValue(a, key);
    const vb = sortValue(b, key);
    if (va === null && vb === null) return a.shape_id - b.shape_id;
    if (va === null) return 1;   // missing values last either way
    if (vb === null) return -1;
    if (va < vb) return -dir;
    if (va > vb) return dir;
    return a.shape_id - b.shape_id;
  });
  const body = $("ui-subjects").tBodies[0];
  body.replaceChildren(...rows.map((s) => {
    const attached = isAttached(s);
    const tr = el("tr", {
      "data-shape-id": String(s.shape_id),
      "data-status": statusOf(s),
      class: [attached ? "" : "unattached", isLeaf(s) ? "leaf" : "", s.shape_id === state.selected ? "selected" : ""].join(" ").trim(),
      title: isLeaf(s) && s.reason ? s.reason : null,
    },
    el("td", { class: "num", text: String(s.shape_id) }),
    el("td", { text: s.name || "" }),
    el("td", { class: "num", text: attached ? String(s.layer) : "unattached" }),
    el("td", { text: s.parent_shape_id === null || s.parent_shape_id === undefined ? "–" : nameOf(s.parent_shape_id) }),
    el("td", { class: "num", text: fmtNum(s.similarity) }),
    el("td", { class: "num", text: fmtNum(s.error) }),
    el("td", { class: "num", text: fmtNum(s.direct_error) }),
    el("td", { class: "num", text: hasNumber(s.confidence) ? s.confidence.toFixed(2) : "–" }),
    el("td", { class: "num", text: fmtNum(s.disagreement) }),
    el("td", { class: "status-cell" }, statusBadgeOf(s)));
    tr.addEventListener("click", () => go(`#/jobs/${state.job.id}/subjects/${s.shape_id}`));
    return tr;
  }));
  for (const th of $("ui-subjects").tHead.rows[0].cells) {
    th.classList.toggle("sorted-asc", th.dataset.sort === key && dir === 1);
    th.classList.toggle("sorted-desc", th.dataset.sort === key && dir === -1);
  }
}

export function setupTable() {
  for (const th of $("ui-subjects").tHead.rows[0].cells) {
    th.addEventListener("click", () => {
      const key = th.dataset.sort;
      // confidence: the least confident first, the ones to look at
      state.sort = { key, dir: state.sort.key === key ? -state.sort.dir : 1 };
      if (state.result) renderTable();
    });
  }
  $("ui-subjects-show").addEventListener("change", (event) => {
    state.filter.show = event.target.value;
    if (state.result) renderTable();
  });
  $("ui-subjects-min-confidence").addEventListener("input", (event) => {
    const text = event.target.value.trim();
    const value = text === "" ? null : Number(text);
    const ok = value === null || (Number.isFinite(value) && value >= 0 && value <= 1);
    event.target.setCustomValidity(ok ? "" : "a number from 0 to 1");
    state.filter.minConfidence = ok ? value : null;
    if (state.result) renderTable();
  });
}

// --- a subject ------------------------------------------------------------------------------
export function number(label, value, field, title) {
  return el("div", { title: title || null },
    el("dt", { text: label }), el("dd", { "data-field": field }, value));
}

export function selectSubject(shapeId) {
  state.selected = shapeId ?? null;
  for (const [id, node] of tv.nodes) node.g.classList.toggle("selected", id === state.selected);
  for (const chip of $("ui-unattached-list").querySelectorAll("button")) {
    chip.classList.toggle("selected", Number(chip.dataset.shapeId) === state.selected);
  }
  for (const tr of $("ui-subjects").tBodies[0].rows) {
    tr.classList.toggle("selected", Number(tr.dataset.shapeId) === state.selected);
  }
  // a shape picked in the tree is where the user looks already; one picked elsewhere (search,
  // table, a link) is brought into view at a readable size
  const zoom = !state.fromTree;
  state.fromTree = false;
  if (state.selected !== null) {
    revealNode(state.selected, { zoom });
    if (zoom) revealChip(state.selected);
  }
  placeLocator();
  const empty = $("ui-subject-empty");
  const body = $("ui-subject-body");
  if (shapeId === null || shapeId === undefined || !state.result) {
    empty.hidden = false;
    body.hidden = true;
    return;
  }
  empty.hidden = true;
  body.hidden = false;
  const r = state.result;
  const title = $("ui-subject-title");
  body.dataset.shapeId = String(shapeId);
  const overlayStatus = $("ui-overlay-status");
  const img = $("ui-overlay");
  if (shapeId === r.root_shape_id) {
    title.textContent = `${nameOf(shapeId)} — the model`;
    $("ui-subject-numbers").replaceChildren(
      number("shape", `#${shapeId}`, "shape_id"),
      number("layer", "1", "layer"),
      number("parent", "– (root)", "parent"));
    $("ui-subject-reason").textContent = "Every other shape is registered from the model, directly or through the tree.";
    renderBestAttempt(null);
    img.hidden = true;
    state.overlayToken += 1;
    overlayStatus.textContent = "";
    return;
  }
  const s = state.subjectsById.get(shapeId);
  if (!s) {
    title.textContent = `Shape ${shapeId}`;
    $("ui-subject-numbers").replaceChildren();
    $("ui-subject-reason").textContent = "This shape is not a subject of this job.";
    renderBestAttempt(null);
    img.hidden = true;
    overlayStatus.textContent = "";
    return;
  }
  const attached = isAttached(s);
  title.textContent = s.name || `Shape ${shapeId}`;
  const parent = s.parent_shape_id;
  const parentValue = parent === null || parent === undefined
    ? "–"
    : el("a", { href: `#/jobs/${state.job.id}/subjects/${parent}`, text: `${nameOf(parent)} (#${parent})` });
  let directValue = fmtNum(s.direct_error);
  if (s.direct_error !== null && s.direct_error !== undefined && s.error) {
    const ratio = s.direct_error / s.error;
    const span = el("span", {
      class: ratio > 1.05 ? "better" : ratio < 0.95 ? "worse" : "",
      text: ` (${fmtNum(ratio, 2)}× tree)`,
      title: "direct CPD's e divided by the tree's e: above 1, the tree registered this shape better",
    });
    directValue = el("span", {}, fmtNum(s.direct_error), span);
  }
  $("ui-subject-numbers").replaceChildren(
    number("shape", `#${shapeId}`, "shape_id"),
    number("layer", attached ? String(s.layer) : "unattached", "layer"),
    number("parent", parentValue, "parent"),
    number("D", fmtNum(s.similarity), "similarity", "shape difference D to the parent (similarity distance)"),
    number("e", fmtNum(s.error), "error", "registration error e (eq. 10) through the tree"),
    number("direct e", directValue, "direct_error", "e of direct CPD from the model"),
    number("confidence", hasNumber(s.confidence) ? s.confidence.toFixed(2) : "–", "confidence",
      "estimated probability that the correspondences are right (the weakest registration on the path from the model)"),
    number("disagreement", fmtNum(s.disagreement), "disagreement",
      "how far apart two registrations that err differently put the model's points, in units of the shape's size: a second sign beside confidence"),
    number("status", statusBadgeOf(s), "status"));
  const path = s.path_shape_ids && s.path_shape_ids.length > 2
    ? ` Path: ${s.path_shape_ids.map(nameOf).join(" → ")}.`
    : "";
  $("ui-subject-reason").textContent = (s.reason ? `${s.reason}.` : "") + path;
  renderBestAttempt(attached ? null : bestRejected(s));
  // in the one-column layout the card is under the tree: bring it into view
  const card = $("ui-subject").getBoundingClientRect();
  if (card.top > window.innerHeight - 80) $("ui-subject").scrollIntoView({ block: "start" });
  loadOverlay(shapeId);
}

// An unattached shape's best rejected registration: the tried one with the lowest e (every
// attempt registers this same subject, so their e compare like with like).
export function bestRejected(s) {
  const tried = (s.attempts || []).filter((a) => !a.accepted && hasNumber(a.error));
  return tried.length ? tried.reduce((a, b) => (b.error < a.error ? b : a)) : null;
}

function renderBestAttempt(attempt) {
  const p = $("ui-subject-attempt");
  p.hidden = attempt === null;
  if (attempt === null) { p.replaceChildren(); return; }
  const from = attempt.member_shape_id ?? null;
  const member = from === null ? `member ${attempt.member}` : nameOf(from);
  const limit = hasNumber(attempt.limit) ? ` (its limit ${fmtNum(attempt.limit)})` : "";
  p.replaceChildren(
    el("strong", { text: "Best rejected attempt: " }),
    `from ${member} at layer ${attempt.layer}, e = ${fmtNum(attempt.error)}${limit}`,
    attempt.reason ? ` — ${attempt.reason}.` : ".",
  );
  p.dataset.member = from === null ? "" : String(from);
}

export async function loadOverlay(shapeId) {
  const token = ++state.overlayToken;
  const img = $("ui-overlay");
  const status = $("ui-overlay-status");
  img.hidden = true;
  img.removeAttribute("data-shape-id");
  status.textContent = "drawing…";
  const box = $("ui-subject");
  // as wide as the card, but not so narrow that the panels' titles run into each other
  // (an unattached subject's or a leaf's title has its reason, a long one); the <img> scales down
  const s = state.subjectsById.get(shapeId);
  const least = s && (s.attached === false || isLeaf(s)) ? 1100 : 700;
  const px = Math.max(least, Math.min(1600, Math.round((box.clientWidth * (window.devicePixelRatio || 1)) / 100) * 100));
  const ydir = $("ui-ydir").value;
  const query = `?width=${px}` + (ydir ? `&y_down=${ydir}` : "");
  try {
    const blob = await api(`/v1/jobs/${state.job.id}/result/subjects/${shapeId}/overlay.png${query}`, { as: "blob" });
    if (token !== state.overlayToken) return;
    img.alt = `${nameOf(shapeId)} with the model warped onto it`;
    img.addEventListener("load", () => img.setAttribute("data-shape-id", String(shapeId)), { once: true });
    showBlob(img, "overlay", blob);
    $("ui-overlay-link").href = img.src;
    status.textContent = "Click the picture to open it at full size.";
  } catch (e) {
    if (token === state.overlayToken) status.textContent = `No picture: ${e.message}`;
  }
}

// fetched with the key like everything else, then saved through a blob: link
export async function download(what) {
  if (!state.job) return;
  const id = state.job.id;
  const path = what === "result.json" ? `/v1/jobs/${id}/result?full=true` : `/v1/jobs/${id}/result/${what}`;
  try {
    const blob = await api(path, { as: "blob" });
    const url = URL.createObjectURL(blob);
    const a = el("a", { href: url, download: `regtree-job-${id}-${what}` });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60_000);
  } catch (e) {
    notice(`Could not download ${what}: ${e.message}`);
  }
}
