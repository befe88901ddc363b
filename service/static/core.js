// regtree results page: the shared core (constants, state, the API, the key form, formatting).

export const KEY_STORAGE = "regtree.apiKey";
export const POLL_MS = 1000;
export const LIST_POLL_MS = 3000;
export const METHOD_LABELS = { dynamic_tree: "dynamic tree", static_tree: "static tree", direct: "direct CPD", grouping: "grouping by mould" };
export const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);

export const $ = (id) => document.getElementById(id);
export const el = (tag, attrs = {}, ...children) => {
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
export const state = {
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

export const apiKey = () => sessionStorage.getItem(KEY_STORAGE) || "";

export async function api(path, { method = "GET", as = "json" } = {}) {
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

export async function problemOf(response) {
  try {
    return await response.json();
  } catch {
    return { detail: `HTTP ${response.status}` };
  }
}

export function setConn(text, bad) {
  const c = $("ui-conn");
  c.textContent = text;
  c.classList.toggle("bad", !!bad);
}

export function notice(text) {
  const n = $("ui-notice");
  n.textContent = text || "";
  n.hidden = !text;
}

// --- API key --------------------------------------------------------------------------------
export function askForKey(message) {
  state.needKey = true;
  $("ui-key-message").textContent = message;
  $("ui-key-form").hidden = false;
  $("ui-key-input").focus();
  stopTimers();
}

// `onKey`: what to do once a key is entered (reload everything)
export function setupKeyForm(onKey) {
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
    onKey();
  });
  $("ui-key-forget").addEventListener("click", () => {
    sessionStorage.removeItem(KEY_STORAGE);
    $("ui-key-input").value = "";
    $("ui-key-message").textContent = "Key forgotten.";
  });
  $("ui-key-close").addEventListener("click", () => { $("ui-key-form").hidden = true; });
}

// --- formatting -----------------------------------------------------------------------------
// One number format for the whole page: `digits` significant digits, trailing zeros kept, in
// decimals from 1e-6 to 1e5 (e and D of a job span 1e-6 to 1: "0.00000815", "0.0170", "0.123"
// line up in a column and compare at a glance) and in exponent form only outside that range.
export function fmtNum(v, digits = 3) {
  if (v === null || v === undefined || Number.isNaN(v)) return "–";
  if (v === 0) return "0";
  const a = Math.abs(v);
  if (a >= 1e-6 && a < 1e5) {
    const magnitude = Math.floor(Math.log10(Number(a.toPrecision(digits))));
    return v.toFixed(Math.max(0, digits - 1 - magnitude));
  }
  return v.toExponential(digits - 1);
}
export function fmtTime(iso) {
  if (!iso) return "–";
  const d = new Date(iso);
  const p = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())} ${p(d.getHours())}:${p(d.getMinutes())}`;
}
export function fmtSeconds(s) {
  if (s < 60) return `${s.toFixed(1)} s`;
  const m = Math.floor(s / 60);
  return `${m} min ${Math.round(s - 60 * m)} s`;
}
export function fmtDuration(a, b) {
  if (!a || !b) return "–";
  return fmtSeconds((new Date(b) - new Date(a)) / 1000);
}
export const methodLabel = (m) => METHOD_LABELS[m] || String(m || "").replace(/_/g, " ");
export const statusBadge = (status) => el("span", { class: `status ${status}`, text: status, "data-status": status });
export function progressText(job) {
  const p = job.progress || {};
  const stage = p.stage ? p.stage.replace(/_/g, " ") : job.status;
  let text = p.total ? `${stage} ${p.done}/${p.total}` : stage;
  // the worker's estimate of the whole job (the same figures as `regtree watch`)
  if (p.fraction != null && !TERMINAL.has(job.status)) {
    text += ` · overall ${Math.floor(100 * p.fraction)}%`;
    if (p.seconds_left != null) text += `, about ${fmtSeconds(Math.ceil(p.seconds_left))} left`;
  }
  return text;
}

export function go(hash) {
  if (location.hash !== hash) location.hash = hash;
}

export function nameOf(shapeId) {
  const r = state.result;
  if (!r) return `#${shapeId}`;
  const s = state.subjectsById.get(shapeId);
  if (s && s.name) return s.name;
  return state.namesById.get(shapeId) ?? `#${shapeId}`;
}

// --- a subject, as the server states it -----------------------------------------------------
// a low-confidence leaf is attached (it has a parent and a registration) but is no tree member;
// the server states `attached` for every subject (service.contract.names.is_attached)
export const isAttached = (s) => s.attached === true;
export const isLeaf = (s) => s.leaf === true;
export const hasNumber = (v) => typeof v === "number" && Number.isFinite(v);

// --- pictures -------------------------------------------------------------------------------
export function showBlob(img, slot, blob) {
  if (state.objectUrls[slot]) URL.revokeObjectURL(state.objectUrls[slot]);
  state.objectUrls[slot] = URL.createObjectURL(blob);
  img.src = state.objectUrls[slot];
  img.hidden = false;
}

export function stopTimers() {
  clearTimeout(state.jobTimer);
  clearTimeout(state.listTimer);
}
