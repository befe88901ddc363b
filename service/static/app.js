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
    namesById: new Map(),
    fromTree: false,       // the selection was made by clicking the tree (no zoom to it)
    selected: null,        // selected shape id
    sort: { key: "shape_id", dir: 1 },
    filter: { show: "all", minConfidence: null },  // which subjects the table lists
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
    resetTreeView();
    if (window.regtreeGrouping) window.regtreeGrouping.hide();
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
    if (job.status === "succeeded" && job.method === "grouping" && window.regtreeGrouping) {
      window.regtreeGrouping.show(job, api, () => token === state.loadToken);
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
    const ids = result.shape_ids || [];
    state.namesById = new Map(ids.map((id, i) => [id, (result.names || [])[i] ?? `#${id}`]));
    $("ui-result").hidden = false;
    renderFacts();
    renderTable();
    // the tree is asked for first: the service draws one picture at a time
    const tree = loadTree(token);
    loadSummary(token);
    await tree;
    if (token === state.loadToken) selectSubject(state.route.subjectId);
  }

  function nameOf(shapeId) {
    const r = state.result;
    if (!r) return `#${shapeId}`;
    const s = state.subjectsById.get(shapeId);
    if (s && s.name) return s.name;
    return state.namesById.get(shapeId) ?? `#${shapeId}`;
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

  // --- the tree: zoom, pan, fit, search --------------------------------------------------------
  // The server draws the tree (tree.svg, matplotlib); the page shows it in a fixed-size box and
  // moves a viewBox over it: zoom with the wheel, the buttons or + and −, pan by dragging or with
  // the arrow keys, 0 fits the whole tree. The picture's "unattached" box is taken out of it and
  // listed as buttons under the tree, so those names stay readable at any zoom.
  const TREE = {
    MAX_SCALE: 4,          // 4x the picture's natural size
    READABLE: 1,           // a found shape is shown at least at natural size (9 pt names)
    LOCATOR_BELOW: 0.75,   // under this scale a ring marks the selected shape
    PAD: 10,               // px kept free around the fitted tree
    ANIMATE_MS: 180,
  };
  const tv = {
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
  const reducedMotion = () => window.matchMedia && matchMedia("(prefers-reduced-motion: reduce)").matches;

  async function loadTree(token) {
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
    // a wide tree takes more of the page's width (before the box is measured)
    box.closest(".panes").classList.toggle("big-tree", content.w * tv.unitPx > 1200);
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

  function resetTreeView() {
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
    clearSearch();
  }

  // the box: as wide as its column; as high as the tree at that width, within limits
  function sizeTreeBox() {
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

  const scaleOf = (v = tv.view) => tv.boxW / (v.w * tv.unitPx);
  const viewCentre = (v = tv.view) => [v.x + v.w / 2, v.y + v.h / 2];
  const contentCentre = () => [tv.content.x + tv.content.w / 2, tv.content.y + tv.content.h / 2];
  function fitScale() {
    const c = tv.content;
    return Math.min((tv.boxW - 2 * TREE.PAD) / (c.w * tv.unitPx), (tv.boxH - 2 * TREE.PAD) / (c.h * tv.unitPx));
  }
  const minScale = () => Math.min(0.8 * fitScale(), 1);
  const clampScale = (s) => Math.min(TREE.MAX_SCALE, Math.max(minScale(), s));
  function viewAt(scale, cx, cy) {
    const s = clampScale(scale);
    const w = tv.boxW / (s * tv.unitPx);
    const h = tv.boxH / (s * tv.unitPx);
    return { x: cx - w / 2, y: cy - h / 2, w, h };
  }
  // keep the view's centre over the tree, so it cannot be lost by panning
  function clampView(v) {
    const c = tv.content;
    const [cx, cy] = viewCentre(v);
    const x = Math.min(c.x + c.w, Math.max(c.x, cx));
    const y = Math.min(c.y + c.h, Math.max(c.y, cy));
    return { ...v, x: v.x + (x - cx), y: v.y + (y - cy) };
  }

  function setView(v) {
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
  function moving() {
    if (!tv.box) return;
    tv.box.classList.add("moving");
    clearTimeout(tv.still);
    tv.still = setTimeout(() => tv.box && tv.box.classList.remove("moving"), 200);
  }

  // move to a view, in a few frames unless the user prefers no motion
  function moveTo(target, animate = true) {
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
  function zoomBy(factor, px = tv.boxW / 2, py = tv.boxH / 2, animate = false) {
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
  function zoomFit(animate = true) {
    if (!tv.view) return;
    tv.fitted = true;
    moveTo(viewAt(fitScale(), ...contentCentre()), animate);
  }
  function zoomActual() {
    if (!tv.view) return;
    tv.fitted = false;
    const sel = state.selected !== null ? tv.nodes.get(state.selected) : null;
    moveTo(viewAt(1, ...(sel ? nodeCentre(sel.box) : viewCentre())));
  }
  function panBy(dxPx, dyPx) {
    if (!tv.view) return;
    const k = tv.view.w / tv.boxW;
    tv.fitted = false;
    setView({ ...tv.view, x: tv.view.x + dxPx * k, y: tv.view.y + dyPx * k });
  }

  const nodeCentre = (b) => [b.x + b.width / 2, b.y + b.height / 2];

  // bring a node into view: centred when outside it; with zoom, at a readable scale at least
  function revealNode(shapeId, { zoom = false, animate = true } = {}) {
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

  function flash(g) {
    g.classList.remove("rt-flash");
    void g.getBoundingClientRect(); // a style and layout pass in between restarts the animation
    g.classList.add("rt-flash");
    setTimeout(() => g.classList.remove("rt-flash"), 1600);
  }

  // a ring over the selected shape when the tree is drawn too small to see its highlight
  function placeLocator() {
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
  function makeNodesClickable(svg) {
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

  function openFromTree(shapeId) {
    state.fromTree = true;
    openSubject(shapeId);
  }

  // open a subject (route), or only bring it into view when it is open already
  function openSubject(shapeId, { zoom = false } = {}) {
    if (!state.job) return;
    const hash = `#/jobs/${state.job.id}/subjects/${shapeId}`;
    if (location.hash === hash) {
      revealNode(shapeId, { zoom });
      revealChip(shapeId);
      return;
    }
    go(hash);  // selectSubject brings it into view, zoomed in
  }

  function setupTreeView() {
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
    setupSearch();
  }

  // --- unattached shapes, as buttons under the tree --------------------------------------------
  // a low-confidence leaf is attached (it has a parent and a registration) but is no tree member;
  // the server states `attached` for every subject (service.contract.names.is_attached)
  const isAttached = (s) => s.attached === true;
  const isLeaf = (s) => s.leaf === true;
  const hasNumber = (v) => typeof v === "number" && Number.isFinite(v);
  const STATUS = { tree: "tree member", leaf: "low-confidence leaf", unattached: "unattached" };
  const statusOf = (s) => s.status; // the server states it: tree, leaf or unattached
  const statusBadgeOf = (s) => {
    const status = statusOf(s);
    return el("span", { class: `badge ${status}`, "data-status": status, text: STATUS[status] });
  };

  function renderUnattached() {
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

  function revealChip(shapeId) {
    const chip = $("ui-unattached-list").querySelector(`button[data-shape-id="${shapeId}"]`);
    if (chip) chip.scrollIntoView({ block: "nearest", inline: "nearest" });
  }

  // --- search by name ----------------------------------------------------------------------------
  const SEARCH_SHOWN = 50;
  const search = { matches: [], active: -1 };

  function allShapes() {
    const r = state.result;
    if (!r) return [];
    const out = [{ id: r.root_shape_id, name: nameOf(r.root_shape_id), where: "model" }];
    for (const s of r.subjects) {
      const where = isAttached(s) ? `layer ${s.layer}${isLeaf(s) ? " · leaf" : ""}` : "unattached";
      out.push({ id: s.shape_id, name: s.name || `#${s.shape_id}`, where });
    }
    return out;
  }

  const fold = (text) => text.normalize("NFKC").toLocaleLowerCase();

  function findShapes(query) {
    const q = fold(query.trim());
    if (!q) return [];
    const found = [];
    for (const shape of allShapes()) {
      const at = fold(shape.name).indexOf(q);
      if (at >= 0) found.push({ ...shape, at });
    }
    // names starting with the query first, then shorter names, then the document's order
    return found.sort((a, b) => (b.at === 0) - (a.at === 0) || a.name.length - b.name.length);
  }

  function markMatches(ids) {
    for (const [id, node] of tv.nodes) node.g.classList.toggle("rt-match", ids.has(id));
    for (const chip of $("ui-unattached-list").querySelectorAll("button")) {
      chip.classList.toggle("match", ids.has(Number(chip.dataset.shapeId)));
    }
  }

  function highlighted(name, query) {
    const q = fold(query.trim());
    const at = fold(name).indexOf(q);
    // NFKC may change lengths: fall back to the plain name when the fold does not line up
    if (at < 0 || fold(name).length !== name.length) return [name];
    return [name.slice(0, at), el("mark", { text: name.slice(at, at + q.length) }), name.slice(at + q.length)];
  }

  function renderMatches(query) {
    const list = $("ui-tree-matches");
    const input = $("ui-tree-search");
    const shown = search.matches.slice(0, SEARCH_SHOWN);
    list.replaceChildren(...shown.map((m, i) => el("li", {
      id: `ui-match-${i}`,
      role: "option",
      class: i === search.active ? "active" : "",
      "aria-selected": i === search.active ? "true" : "false",
      "data-shape-id": String(m.id),
      onmousedown: (event) => { event.preventDefault(); pickMatch(i); },
    }, el("span", { class: "name" }, ...highlighted(m.name, query)), el("span", { class: "where", text: m.where }))));
    if (search.matches.length > SEARCH_SHOWN) {
      list.append(el("li", { class: "more", role: "presentation", text: `${search.matches.length - SEARCH_SHOWN} more: type more of the name` }));
    }
    const open = !!query.trim() && document.activeElement === input;
    list.hidden = !open;
    input.setAttribute("aria-expanded", open ? "true" : "false");
    if (search.active >= 0) input.setAttribute("aria-activedescendant", `ui-match-${search.active}`);
    else input.removeAttribute("aria-activedescendant");
    const n = search.matches.length;
    $("ui-tree-found").textContent = !query.trim() ? "" : n ? `${n} match${n === 1 ? "" : "es"}` : "no shape has that in its name";
    const activeItem = list.children[search.active];
    if (activeItem) activeItem.scrollIntoView({ block: "nearest" });
  }

  function onSearchInput() {
    const query = $("ui-tree-search").value;
    search.matches = findShapes(query);
    search.active = search.matches.length ? 0 : -1;
    markMatches(new Set(search.matches.map((m) => m.id)));
    renderMatches(query);
  }

  function pickMatch(i) {
    const m = search.matches[i];
    if (!m) return;
    search.active = i;
    const list = $("ui-tree-matches");
    list.hidden = true;
    $("ui-tree-search").setAttribute("aria-expanded", "false");
    openSubject(m.id, { zoom: true });
  }

  function clearSearch() {
    const input = $("ui-tree-search");
    input.value = "";
    search.matches = [];
    search.active = -1;
    $("ui-tree-matches").hidden = true;
    input.setAttribute("aria-expanded", "false");
    $("ui-tree-found").textContent = "";
    markMatches(new Set());
  }

  function setupSearch() {
    const input = $("ui-tree-search");
    input.addEventListener("input", onSearchInput);
    input.addEventListener("focus", () => { if (input.value.trim()) renderMatches(input.value); });
    input.addEventListener("blur", () => { $("ui-tree-matches").hidden = true; input.setAttribute("aria-expanded", "false"); });
    input.addEventListener("keydown", (event) => {
      const n = Math.min(search.matches.length, SEARCH_SHOWN);
      if (event.key === "ArrowDown" || event.key === "ArrowUp") {
        event.preventDefault();
        if (!n) return;
        search.active = (search.active + (event.key === "ArrowDown" ? 1 : n - 1)) % n;
        renderMatches(input.value);
        // the active match is shown in the tree as the user walks the list
        revealNode(search.matches[search.active].id, { zoom: true });
      } else if (event.key === "Enter") {
        event.preventDefault();
        if (search.matches.length) pickMatch(Math.max(search.active, 0));
      } else if (event.key === "Escape") {
        if (!$("ui-tree-matches").hidden) {
          $("ui-tree-matches").hidden = true;
          input.setAttribute("aria-expanded", "false");
        } else {
          clearSearch();
        }
      }
    });
    // "/" anywhere on the page (outside a field) goes to the search box
    document.addEventListener("keydown", (event) => {
      if (event.key !== "/" || event.ctrlKey || event.metaKey || event.altKey) return;
      const t = event.target;
      if (t && (t.isContentEditable || /^(INPUT|TEXTAREA|SELECT)$/.test(t.tagName))) return;
      if ($("ui-result").hidden) return;
      event.preventDefault();
      input.focus();
      input.select();
    });
  }

  // --- subjects table -------------------------------------------------------------------------
  function sortValue(s, key) {
    if (key === "parent") return s.parent_shape_id === null || s.parent_shape_id === undefined ? "" : nameOf(s.parent_shape_id);
    if (key === "status") return ["tree", "leaf", "unattached"].indexOf(statusOf(s));
    const v = s[key];
    return v === null || v === undefined ? null : v;
  }

  // the subjects the table's filter lets through
  function shownSubjects() {
    const { show, minConfidence } = state.filter;
    return state.result.subjects.filter((s) => (show === "all" || statusOf(s) === show)
      && (minConfidence === null || (hasNumber(s.confidence) && s.confidence >= minConfidence)));
  }

  function renderTable() {
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
      el("td", { class: "status-cell" }, statusBadgeOf(s)));
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
  function number(label, value, field, title) {
    return el("div", { title: title || null },
      el("dt", { text: label }), el("dd", { "data-field": field }, value));
  }

  function selectSubject(shapeId) {
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
      number("status", statusBadgeOf(s), "status"));
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
    setupTreeView();
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
