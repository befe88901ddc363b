// regtree results page: vanilla JavaScript, no build step, no third-party code.
//
// Everything comes from the /v1 JSON API and its picture routes. Routes live in the URL hash:
//   #/                          all jobs
//   #/collections/<id>          a collection's jobs
//   #/jobs/<id>                 a job (progress while it runs, its tree once it has succeeded)
//   #/jobs/<id>/subjects/<sid>  the same, with one subject opened
// With an API key configured on the service, the page asks for it on the first 401, keeps it
// in sessionStorage and sends it as X-API-Key; pictures are fetched the same way and shown
// through blob: URLs (an <img src> could not send the header).
// An ES module (no build step): core.js, tree.js, search.js and subjects.js hold the parts.

import { $, LIST_POLL_MS, POLL_MS, TERMINAL, api, el, fmtDuration, fmtNum, fmtTime, methodLabel, nameOf, notice, progressText, setupKeyForm, showBlob, state, statusBadge, stopTimers } from "./core.js";
import * as grouping from "./grouping.js";
import { clearSearch, setupSearch } from "./search.js";
import { download, loadOverlay, renderTable, selectSubject, setupTable } from "./subjects.js";
import { loadTree, resetTreeView, setupTreeView } from "./tree.js";

// --- routing --------------------------------------------------------------------------------
function parseRoute() {
  const parts = location.hash.replace(/^#\/?/, "").split("/").filter(Boolean);
  if (parts[0] === "jobs" && /^\d+$/.test(parts[1] || "")) {
    const subject = parts[2] === "subjects" && /^\d+$/.test(parts[3] || "") ? Number(parts[3]) : null;
    return { view: "job", jobId: Number(parts[1]), subjectId: subject };
  }
  if (parts[0] === "collections" && /^\d+$/.test(parts[1] || "")) {
    return { view: "collection", collectionId: Number(parts[1]) };
  }
  return { view: "home" };
}

async function onRoute() {
  const route = parseRoute();
  const previous = state.route;
  state.route = route;
  notice("");
  if (route.view === "job") {
    if (previous.view === "job" && previous.jobId === route.jobId && state.job) {
      selectSubject(route.subjectId);
      return;
    }
    await openJob(route.jobId);
  } else {
    closeJob();
    state.collectionId = route.view === "collection" ? route.collectionId : null;
    renderCollections();
    await loadJobs();
  }
}

// --- sidebar --------------------------------------------------------------------------------
// The first `want` items of a list, in pages of the server's own default size (an
// operator may set max_page_size below `want`; asking for more would be refused).
async function listPage(path, want) {
  const sep = path.includes("?") ? "&" : "?";
  let page = await api(path);
  const items = page.items.slice();
  while (page.items.length && items.length < Math.min(want, page.total)) {
    page = await api(`${path}${sep}offset=${items.length}`);
    items.push(...page.items);
  }
  return { items: items.slice(0, want), total: page.total };
}

async function loadCollections() {
  try {
    const page = await listPage("/v1/collections", 500);
    state.collections = page.items;
    state.collectionsTotal = page.total;
  } catch (e) {
    if (e.status !== 401) notice(`Could not list collections: ${e.message}`);
    return;
  }
  renderCollections();
}

function renderCollections() {
  const list = $("ui-collections");
  list.replaceChildren();
  list.append(el("li", {}, el("a", {
    href: "#/", class: state.collectionId === null ? "active" : "", "data-collection-id": "all",
  }, el("span", { class: "name", text: "All jobs" }))));
  for (const c of state.collections) {
    list.append(el("li", {}, el("a", {
      href: `#/collections/${c.id}`,
      class: state.collectionId === c.id ? "active" : "",
      "data-collection-id": String(c.id),
      title: c.description || c.name,
    },
    el("div", { class: "title" }, el("span", { class: "name", text: c.name })),
    el("div", { class: "sub", text: `#${c.id} · ${c.n_shapes} shape${c.n_shapes === 1 ? "" : "s"}` }))));
  }
  if (!state.collections.length) list.append(el("li", { class: "empty", text: "No collections yet." }));
  if (state.collectionsTotal > state.collections.length) {
    list.append(el("li", { class: "empty", text: `${state.collectionsTotal - state.collections.length} more not shown` }));
  }
}

async function loadJobs() {
  const cid = state.collectionId;
  const query = cid === null ? "" : `?collection_id=${cid}`;
  let page;
  try {
    page = await listPage(`/v1/jobs${query}`, 100);
  } catch (e) {
    if (e.status !== 401) notice(`Could not list jobs: ${e.message}`);
    return;
  }
  if (cid !== state.collectionId) return;  // the user moved on meanwhile
  state.jobs = page.items;
  renderJobs(page.total);
  scheduleListPoll();
}

function renderJobs(total) {
  const c = state.collections.find((x) => x.id === state.collectionId);
  $("ui-jobs-title").textContent = state.collectionId === null ? "Jobs" : `Jobs of ${c ? c.name : `#${state.collectionId}`}`;
  const list = $("ui-jobs");
  list.replaceChildren();
  for (const job of state.jobs) {
    const openId = state.job ? state.job.id : null;
    const item = el("a", {
      href: `#/jobs/${job.id}`, class: job.id === openId ? "active" : "", "data-job-id": String(job.id),
    },
    el("div", { class: "title" }, el("span", { class: "name", text: `Job ${job.id}` }), statusBadge(job.status)),
    el("div", { class: "sub", "data-field": "names", text: jobNames(job) }),
    el("div", { class: "sub", text: `${methodLabel(job.method)} · ${job.n_shapes} shapes · ${fmtTime(job.created_at)}` }));
    if (!TERMINAL.has(job.status)) {
      const p = job.progress || {};
      item.append(el("progress", { max: p.total || 1, value: p.total ? p.done : 0 }));
    }
    list.append(el("li", {}, item));
  }
  if (!state.jobs.length) list.append(el("li", { class: "empty", text: "No jobs yet." }));
  if (total > state.jobs.length) list.append(el("li", { class: "empty", text: `${total - state.jobs.length} older not shown` }));
}

// "collection · model shape": what a job registered, by name (ids when a name is gone)
function jobNames(job) {
  const collection = job.collection_name ?? `collection #${job.collection_id}`;
  if (job.method === "grouping") return `${collection} · grouping by mould`;
  const model = job.model_name ?? `#${job.model_shape_id}`;
  return `${collection} · model ${model}`;
}

function scheduleListPoll() {
  clearTimeout(state.listTimer);
  if (state.needKey) return;
  if (state.jobs.some((j) => !TERMINAL.has(j.status))) {
    state.listTimer = setTimeout(loadJobs, LIST_POLL_MS);
  }
}

// --- a job ----------------------------------------------------------------------------------
function closeJob() {
  clearTimeout(state.jobTimer);
  state.loadToken += 1;
  state.job = null;
  state.result = null;
  state.selected = null;
  resetTreeView();
  clearSearch();
  grouping.hide();
  $("ui-job").hidden = true;
  $("ui-welcome").hidden = false;
}

async function openJob(jobId) {
  closeJob();
  const token = state.loadToken;
  $("ui-welcome").hidden = true;
  $("ui-job").hidden = false;
  $("ui-result").hidden = true;
  $("ui-job-title").textContent = `Job ${jobId}`;
  $("ui-job-status").replaceChildren();
  $("ui-job-facts").replaceChildren();
  $("ui-job-error").hidden = true;
  $("ui-job-progress").hidden = true;
  $("ui-job-cancel").hidden = true;
  await pollJob(token);
}

async function pollJob(token) {
  let job;
  try {
    job = await api(`/v1/jobs/${state.route.jobId}`);
  } catch (e) {
    if (token !== state.loadToken) return;
    if (e.status === 404) {
      // a clear state for a link to a job this service does not have
      $("ui-job-title").textContent = `No job ${state.route.jobId}`;
      $("ui-job-status").replaceChildren(el("span", { class: "status missing", text: "not found", "data-status": "missing" }));
      const err = $("ui-job-error");
      err.hidden = false;
      err.dataset.state = "not-found";
      err.textContent = `This service has no job ${state.route.jobId}: it was deleted with its `
        + "collection, or the link comes from another service. Pick a job on the left, or see all jobs.";
      err.append(" ", el("a", { href: "#/", text: "All jobs" }));
    } else if (e.status !== 401) {
      notice(`Could not read the job: ${e.message}`);
      state.jobTimer = setTimeout(() => pollJob(token), 3 * POLL_MS);
    }
    return;
  }
  if (token !== state.loadToken) return;
  const firstTime = !state.job;
  state.job = job;
  if (firstTime || state.collectionId !== job.collection_id) {
    state.collectionId = job.collection_id;
    renderCollections();
    loadJobs();
  } else {
    // keep the sidebar's copy of this job fresh without another request
    const i = state.jobs.findIndex((j) => j.id === job.id);
    if (i >= 0 && state.jobs[i].status !== job.status) { state.jobs[i] = job; renderJobs(); }
  }
  renderJobHeader(job);
  if (job.status === "succeeded" && job.method === "grouping") {
    grouping.show(job, api, () => token === state.loadToken);
  } else if (job.status === "succeeded") {
    if (!state.result) await loadResult(token);
  } else if (!TERMINAL.has(job.status) && !state.needKey) {
    state.jobTimer = setTimeout(() => pollJob(token), POLL_MS);
  }
}

function renderJobHeader(job) {
  $("ui-job-title").textContent = `Job ${job.id}: ${methodLabel(job.method)}`;
  $("ui-job-status").replaceChildren(statusBadge(job.status));
  const running = !TERMINAL.has(job.status);
  $("ui-job-progress").hidden = !running;
  if (running) {
    const p = job.progress || {};
    const bar = $("ui-job-progressbar");
    if (p.fraction != null) { bar.max = 1; bar.value = p.fraction; }
    else if (p.total) { bar.max = p.total; bar.value = p.done; } else { bar.removeAttribute("value"); }
    $("ui-job-progresstext").textContent = progressText(job) + (job.cancel_requested ? " — cancelling" : "");
  }
  $("ui-job-cancel").hidden = !running || job.cancel_requested;
  const err = $("ui-job-error");
  err.hidden = !job.error;
  err.textContent = job.error ? `Error: ${job.error}` : "";
  renderFacts();
}

function fact(label, value, title) {
  return el("div", { title: title || null }, el("dt", { text: label }), el("dd", { text: value }));
}

function renderFacts() {
  const job = state.job;
  if (!job) return;
  const c = state.collections.find((x) => x.id === job.collection_id);
  const r = state.result;
  const items = [
    fact("collection", c ? `${c.name} (#${c.id})` : `#${job.collection_id}`),
    // a grouping has no model (its model_shape_id is null)
    job.model_shape_id == null ? null
      : fact("model shape", `${job.model_name ?? nameOf(job.model_shape_id)} (#${job.model_shape_id})`),
    fact("shapes", String(job.n_shapes)),
    fact("created", fmtTime(job.created_at)),
    TERMINAL.has(job.status)
      ? fact("ran for", fmtDuration(job.started_at, job.finished_at))
      : fact("running for", fmtDuration(job.started_at, new Date().toISOString())),
  ];
  if (r && r.summary) {
    const s = r.summary;
    if (s.attached !== undefined) items.push(fact("attached", `${s.attached} of ${s.subjects}`));
    if (s.leaves) {
      items.push(fact("low-confidence leaves", String(s.leaves),
        "attached shapes the tree could not accept: each got its best registration, as a leaf (never a parent)"));
    }
    if (s.depth !== undefined) items.push(fact("depth", String(s.depth)));
    if (s.all) items.push(fact("mean e, tree", fmtNum(s.all.mean)));
    if (s.direct && s.direct.all) items.push(fact("mean e, direct", fmtNum(s.direct.all.mean)));
  }
  const th = r && r.thresholds;
  if (th) {
    if (th.similarity !== undefined) items.push(fact("D threshold", fmtNum(th.similarity), th.similarity_rule));
    if (th.error !== undefined) items.push(fact("e threshold", fmtNum(th.error), th.error_rule));
  }
  $("ui-job-facts").replaceChildren(...items.filter((x) => x !== null));
}

async function loadResult(token) {
  let result;
  try {
    result = await api(`/v1/jobs/${state.job.id}/result`);
  } catch (e) {
    if (token === state.loadToken && e.status !== 401) notice(`Could not read the result: ${e.message}`);
    return;
  }
  if (token !== state.loadToken) return;
  state.result = result;
  state.subjectsById = new Map(result.subjects.map((s) => [s.shape_id, s]));
  const ids = result.shape_ids || [];
  state.namesById = new Map(ids.map((id, i) => [id, (result.names || [])[i] ?? `#${id}`]));
  $("ui-result").hidden = false;
  renderFacts();
  renderTable();
  // the tree is asked for first: the service draws one picture at a time
  const tree = loadTree(token);
  clearSearch();  // a new tree: the search over its shapes starts empty
  loadSummary(token);
  await tree;
  if (token === state.loadToken) selectSubject(state.route.subjectId);
}

async function loadSummary(token) {
  const img = $("ui-summary");
  img.hidden = true;
  $("ui-summary-status").textContent = "drawing…";
  try {
    const blob = await api(`/v1/jobs/${state.job.id}/result/summary.png`, { as: "blob" });
    if (token !== state.loadToken) return;
    showBlob(img, "summary", blob);
    img.alt = `e per layer for job ${state.job.id}`;
    $("ui-summary-status").textContent = "";
  } catch (e) {
    if (token === state.loadToken) $("ui-summary-status").textContent = `No picture: ${e.message}`;
  }
}

// --- start ----------------------------------------------------------------------------------
async function refreshAll() {
  stopTimers();
  state.route = { view: "none" };
  await loadCollections();
  await onRoute();
}

function start() {
  setupKeyForm(refreshAll);
  setupTable();
  setupTreeView();
  setupSearch();
  $("ui-job-cancel").addEventListener("click", async () => {
    if (!state.job || !confirm(`Cancel job ${state.job.id}?`)) return;
    try {
      await api(`/v1/jobs/${state.job.id}/cancel`, { method: "POST" });
    } catch (e) {
      notice(`Could not cancel: ${e.message}`);
    }
  });
  for (const link of document.querySelectorAll("a[data-download]")) {
    link.addEventListener("click", (event) => {
      event.preventDefault();
      download(link.dataset.download);
    });
  }
  $("ui-ydir").addEventListener("change", () => {
    if (state.selected !== null && state.selected !== state.result?.root_shape_id) loadOverlay(state.selected);
  });
  window.addEventListener("hashchange", onRoute);
  refreshAll();
}

start();
