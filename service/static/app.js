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
"use strict";

(() => {
  const KEY_STORAGE = "regtree.apiKey";
  const POLL_MS = 1000;
  const LIST_POLL_MS = 3000;
  const METHOD_LABELS = { dynamic_tree: "dynamic tree", static_tree: "static tree", direct: "direct CPD" };
  const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);

  const $ = (id) => document.getElementById(id);
  const el = (tag, attrs = {}, ...children) => {
    const node = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs)) {
      if (v === null || v === undefined || v === false) continue;
      if (k === "class") node.className = v;
      else if (k === "text") node.textContent = v;
      else if (k.startsWith("data-")) node.setAttribute(k, v);
      else if (k in node) node[k] = v;
      else node.setAttribute(k, v);
    }
    for (const c of children) if (c !== null && c !== undefined) node.append(c);
    return node;
  };

  // --- state ----------------------------------------------------------------------------------
  const state = {
    route: { view: "home" },
    collectionId: null,   // the collection whose jobs the sidebar lists (null: all)
    collections: [],
    jobs: [],
    job: null,             // the open job (JobOut)
    result: null,          // its result document
    subjectsById: new Map(),
    selected: null,        // selected shape id
    sort: { key: "shape_id", dir: 1 },
    jobTimer: null,
    listTimer: null,
    needKey: false,
    loadToken: 0,          // guards against late answers for a job no longer open
    overlayToken: 0,
    objectUrls: { overlay: null, summary: null },
  };

  // --- API ------------------------------------------------------------------------------------
  class ApiError extends Error {
    constructor(status, problem) {
      super((problem && (problem.detail || problem.title)) || `HTTP ${status}`);
      this.status = status;
      this.problem = problem;
    }
  }

  const apiKey = () => sessionStorage.getItem(KEY_STORAGE) || "";

  async function api(path, { method = "GET", as = "json" } = {}) {
    const headers = { Accept: as === "json" ? "application/json" : "*/*" };
    const key = apiKey();
    if (key) headers["X-API-Key"] = key;
    let response;
    try {
      response = await fetch(path, { method, headers });
    } catch (e) {
      setConn(`service unreachable`, true);
      throw new ApiError(0, { detail: `the service did not answer (${e.message})` });
    }
    if (response.status === 401) {
      askForKey(key ? "The API key was refused. Paste the right key." : "This service needs an API key.");
      throw new ApiError(401, await problemOf(response));
    }
    setConn("", false);
    if (!response.ok) throw new ApiError(response.status, await problemOf(response));
    if (as === "json") return response.json();
    if (as === "text") return response.text();
    return response.blob();
  }

  async function problemOf(response) {
    try {
      return await response.json();
    } catch {
      return { detail: `HTTP ${response.status}` };
    }
  }

  function setConn(text, bad) {
    const c = $("ui-conn");
    c.textContent = text;
    c.classList.toggle("bad", !!bad);
  }

  function notice(text) {
    const n = $("ui-notice");
    n.textContent = text || "";
    n.hidden = !text;
  }

  // --- API key --------------------------------------------------------------------------------
  function askForKey(message) {
    state.needKey = true;
    $("ui-key-message").textContent = message;
    $("ui-key-form").hidden = false;
    $("ui-key-input").focus();
    stopTimers();
  }

  function setupKeyForm() {
    $("ui-key-button").addEventListener("click", () => {
      const form = $("ui-key-form");
      $("ui-key-message").textContent = apiKey()
        ? "An API key is set for this tab. Paste another one to replace it."
        : "Paste the service's API key, if it has one.";
      form.hidden = !form.hidden;
      if (!form.hidden) $("ui-key-input").focus();
    });
    $("ui-key-form").addEventListener("submit", (event) => {
      event.preventDefault();
      const value = $("ui-key-input").value.trim();
      if (!value) return;
      sessionStorage.setItem(KEY_STORAGE, value);
      $("ui-key-input").value = "";
      $("ui-key-form").hidden = true;
      state.needKey = false;
      notice("");
      refreshAll();
    });
    $("ui-key-forget").addEventListener("click", () => {
      sessionStorage.removeItem(KEY_STORAGE);
      $("ui-key-input").value = "";
      $("ui-key-message").textContent = "Key forgotten.";
    });
    $("ui-key-close").addEventListener("click", () => { $("ui-key-form").hidden = true; });
  }

  // --- formatting -----------------------------------------------------------------------------
  function fmtNum(v, digits = 3) {
    if (v === null || v === undefined || Number.isNaN(v)) return "–";
    if (v === 0) return "0";
    const a = Math.abs(v);
    if (a >= 1e-3 && a < 1e4) return Number(v.toPrecision(digits)).toString();
    return v.toExponential(digits - 1);
  }
  function fmtTime(iso) {
    if (!iso) return "–";
    const d = new Date(iso);
    const p = (n) => String(n).padStart(2, "0");
    return `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())} ${p(d.getHours())}:${p(d.getMinutes())}`;
  }
  function fmtDuration(a, b) {
    if (!a || !b) return "–";
    const s = (new Date(b) - new Date(a)) / 1000;
    if (s < 60) return `${s.toFixed(1)} s`;
    const m = Math.floor(s / 60);
    return `${m} min ${Math.round(s - 60 * m)} s`;
  }
  const methodLabel = (m) => METHOD_LABELS[m] || String(m || "").replace(/_/g, " ");
  const statusBadge = (status) => el("span", { class: `status ${status}`, text: status, "data-status": status });
  function progressText(job) {
    const p = job.progress || {};
    const stage = p.stage ? p.stage.replace(/_/g, " ") : job.status;
    return p.total ? `${stage} ${p.done}/${p.total}` : stage;
  }

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

  function go(hash) {
    if (location.hash !== hash) location.hash = hash;
  }

  // --- sidebar --------------------------------------------------------------------------------
  async function loadCollections() {
    try {
      const page = await api("/v1/collections?limit=500");
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
    const query = cid === null ? "" : `&collection_id=${cid}`;
    let page;
    try {
      page = await api(`/v1/jobs?limit=100${query}`);
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
        $("ui-job-title").textContent = `Job ${state.route.jobId} not found`;
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
    if (job.status === "succeeded") {
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
      if (p.total) { bar.max = p.total; bar.value = p.done; } else { bar.removeAttribute("value"); }
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
      fact("model shape", r ? `${nameOf(r.root_shape_id)} (#${job.model_shape_id})` : `#${job.model_shape_id}`),
      fact("shapes", String(job.n_shapes)),
      fact("created", fmtTime(job.created_at)),
      TERMINAL.has(job.status)
        ? fact("ran for", fmtDuration(job.started_at, job.finished_at))
        : fact("running for", fmtDuration(job.started_at, new Date().toISOString())),
    ];
    if (r && r.summary) {
      const s = r.summary;
      if (s.attached !== undefined) items.push(fact("attached", `${s.attached} of ${s.subjects}`));
      if (s.depth !== undefined) items.push(fact("depth", String(s.depth)));
      if (s.all) items.push(fact("mean e, tree", fmtNum(s.all.mean)));
      if (s.direct && s.direct.all) items.push(fact("mean e, direct", fmtNum(s.direct.all.mean)));
    }
    const th = r && r.thresholds;
    if (th) {
      if (th.similarity !== undefined) items.push(fact("D threshold", fmtNum(th.similarity), th.similarity_rule));
      if (th.error !== undefined) items.push(fact("e threshold", fmtNum(th.error), th.error_rule));
    }
    $("ui-job-facts").replaceChildren(...items);
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
    $("ui-result").hidden = false;
    renderFacts();
    renderTable();
    loadSummary(token);
    await loadTree(token);
    if (token === state.loadToken) selectSubject(state.route.subjectId);
  }

  function nameOf(shapeId) {
    const r = state.result;
    if (!r) return `#${shapeId}`;
    const s = state.subjectsById.get(shapeId);
    if (s && s.name) return s.name;
    const i = (r.shape_ids || []).indexOf(shapeId);
    return i >= 0 && r.names ? r.names[i] : `#${shapeId}`;
  }

  // --- pictures -------------------------------------------------------------------------------
  function showBlob(img, slot, blob) {
    if (state.objectUrls[slot]) URL.revokeObjectURL(state.objectUrls[slot]);
    state.objectUrls[slot] = URL.createObjectURL(blob);
    img.src = state.objectUrls[slot];
    img.hidden = false;
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

  async function loadTree(token) {
    const box = $("ui-tree");
    box.replaceChildren(el("p", { class: "hint", text: "drawing the tree…" }));
    let text;
    try {
      text = await api(`/v1/jobs/${state.job.id}/result/tree.svg`, { as: "text" });
    } catch (e) {
      if (token === state.loadToken) box.replaceChildren(el("p", { class: "error", text: `No tree: ${e.message}` }));
      return;
    }
    if (token !== state.loadToken) return;
    const doc = new DOMParser().parseFromString(text, "image/svg+xml");
    const svg = doc.documentElement;
    if (!svg || svg.nodeName !== "svg") {
      box.replaceChildren(el("p", { class: "error", text: "The tree picture could not be read." }));
      return;
    }
    const imported = document.importNode(svg, true);
    // draw at its natural size at most, narrower when the column is narrower
    const naturalPx = parseFloat(svg.getAttribute("width") || "0") * (/pt$/.test(svg.getAttribute("width") || "") ? 4 / 3 : 1);
    imported.removeAttribute("height");
    imported.setAttribute("width", "100%");
    if (naturalPx > 0) {
      imported.style.maxWidth = `${Math.round(naturalPx)}px`;
      // a big tree is not shrunk past legibility: the box scrolls sideways instead
      imported.style.minWidth = `${Math.round(0.6 * naturalPx)}px`;
    }
    imported.setAttribute("role", "img");
    imported.setAttribute("aria-label", `registration tree of job ${state.job.id}`);
    imported.id = "ui-tree-svg";
    box.replaceChildren(imported);
    makeNodesClickable(imported);
    $("ui-tree-hint").hidden = box.scrollWidth <= box.clientWidth + 1;
    revealNode(state.route.subjectId ?? state.result.root_shape_id);
  }

  // scroll a wide tree sideways (only sideways: the page stays put) to centre a node
  function revealNode(shapeId) {
    const box = $("ui-tree");
    const g = box.querySelector(`g.rt-node[data-shape-id="${shapeId}"]`);
    if (!g || box.scrollWidth <= box.clientWidth) return;
    const node = g.getBoundingClientRect();
    const view = box.getBoundingClientRect();
    if (node.left < view.left + 20 || node.right > view.right - 20) {
      box.scrollLeft += node.left + node.width / 2 - (view.left + view.width / 2);
    }
  }

  function makeNodesClickable(svg) {
    const ns = "http://www.w3.org/2000/svg";
    const rootId = state.result.root_shape_id;
    for (const g of svg.querySelectorAll("g[id]")) {
      const m = /^(node|unattached)-(\d+)$/.exec(g.id);
      if (!m) continue;
      const shapeId = Number(m[2]);
      g.classList.add("rt-node");
      g.setAttribute("data-shape-id", String(shapeId));
      g.setAttribute("tabindex", "0");
      g.setAttribute("role", "button");
      g.setAttribute("aria-label", `shape ${nameOf(shapeId)}`);
      // a hit area over the name and the node's marker next to it (above the name; below it
      // for the model, whose name is on top)
      const box = g.getBBox();
      const hit = document.createElementNS(ns, "rect");
      const up = shapeId === rootId ? 3 : 11;
      const down = shapeId === rootId ? 11 : 3;
      hit.setAttribute("x", String(box.x - 3));
      hit.setAttribute("y", String(box.y - up));
      hit.setAttribute("width", String(box.width + 6));
      hit.setAttribute("height", String(box.height + up + down));
      hit.setAttribute("rx", "3");
      hit.setAttribute("class", "rt-hit");
      g.insertBefore(hit, g.firstChild);
      const title = document.createElementNS(ns, "title");
      title.textContent = `${nameOf(shapeId)} (shape ${shapeId})`;
      g.append(title);
      g.addEventListener("click", () => go(`#/jobs/${state.job.id}/subjects/${shapeId}`));
      g.addEventListener("keydown", (event) => {
        if (event.key === "Enter" || event.key === " ") {
          event.preventDefault();
          go(`#/jobs/${state.job.id}/subjects/${shapeId}`);
        }
      });
    }
  }

  // --- subjects table -------------------------------------------------------------------------
  function sortValue(s, key) {
    if (key === "parent") return s.parent_shape_id === null || s.parent_shape_id === undefined ? "" : nameOf(s.parent_shape_id);
    const v = s[key];
    return v === null || v === undefined ? null : v;
  }

  function renderTable() {
    const { key, dir } = state.sort;
    const rows = [...state.result.subjects].sort((a, b) => {
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
      const attached = s.attached !== false && s.layer !== null && s.layer !== undefined;
      const tr = el("tr", {
        "data-shape-id": String(s.shape_id),
        class: [attached ? "" : "unattached", s.shape_id === state.selected ? "selected" : ""].join(" ").trim(),
      },
      el("td", { class: "num", text: String(s.shape_id) }),
      el("td", { text: s.name || "" }),
      el("td", { class: "num", text: attached ? String(s.layer) : "unattached" }),
      el("td", { text: s.parent_shape_id === null || s.parent_shape_id === undefined ? "–" : nameOf(s.parent_shape_id) }),
      el("td", { class: "num", text: fmtNum(s.similarity) }),
      el("td", { class: "num", text: fmtNum(s.error) }),
      el("td", { class: "num", text: fmtNum(s.direct_error) }));
      tr.addEventListener("click", () => go(`#/jobs/${state.job.id}/subjects/${s.shape_id}`));
      return tr;
    }));
    for (const th of $("ui-subjects").tHead.rows[0].cells) {
      th.classList.toggle("sorted-asc", th.dataset.sort === key && dir === 1);
      th.classList.toggle("sorted-desc", th.dataset.sort === key && dir === -1);
    }
  }

  function setupTable() {
    for (const th of $("ui-subjects").tHead.rows[0].cells) {
      th.addEventListener("click", () => {
        const key = th.dataset.sort;
        state.sort = { key, dir: state.sort.key === key ? -state.sort.dir : 1 };
        if (state.result) renderTable();
      });
    }
  }

  // --- a subject ------------------------------------------------------------------------------
  function number(label, value, field, title) {
    return el("div", { title: title || null },
      el("dt", { text: label }), el("dd", { "data-field": field }, value));
  }

  function selectSubject(shapeId) {
    state.selected = shapeId ?? null;
    const svg = $("ui-tree-svg");
    if (svg) {
      for (const g of svg.querySelectorAll(".rt-node")) {
        g.classList.toggle("selected", Number(g.dataset.shapeId) === state.selected);
      }
    }
    for (const tr of $("ui-subjects").tBodies[0].rows) {
      tr.classList.toggle("selected", Number(tr.dataset.shapeId) === state.selected);
    }
    if (state.selected !== null) revealNode(state.selected);
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
      img.hidden = true;
      overlayStatus.textContent = "";
      return;
    }
    const attached = s.attached !== false && s.layer !== null && s.layer !== undefined;
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
      number("direct e", directValue, "direct_error", "e of direct CPD from the model"));
    const path = s.path_shape_ids && s.path_shape_ids.length > 2
      ? ` Path: ${s.path_shape_ids.map(nameOf).join(" → ")}.`
      : "";
    $("ui-subject-reason").textContent = (s.reason ? `${s.reason}.` : "") + path;
    // in the one-column layout the card is under the tree: bring it into view
    const card = $("ui-subject").getBoundingClientRect();
    if (card.top > window.innerHeight - 80) $("ui-subject").scrollIntoView({ block: "start" });
    loadOverlay(shapeId);
  }

  async function loadOverlay(shapeId) {
    const token = ++state.overlayToken;
    const img = $("ui-overlay");
    const status = $("ui-overlay-status");
    img.hidden = true;
    img.removeAttribute("data-shape-id");
    status.textContent = "drawing…";
    const box = $("ui-subject");
    // as wide as the card, but not so narrow that the panels' titles run into each other
    // (an unattached subject's title is its reason, a long one); the <img> scales down
    const s = state.subjectsById.get(shapeId);
    const least = s && s.attached === false ? 1100 : 700;
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
  async function download(what) {
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

  // --- start ----------------------------------------------------------------------------------
  function stopTimers() {
    clearTimeout(state.jobTimer);
    clearTimeout(state.listTimer);
  }

  async function refreshAll() {
    stopTimers();
    state.route = { view: "none" };
    await loadCollections();
    await onRoute();
  }

  function start() {
    setupKeyForm();
    setupTable();
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
})();
