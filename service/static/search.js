// regtree results page: search by name over the tree's shapes.

import { $, el, isAttached, isLeaf, nameOf, state } from "./core.js";
import { openSubject, revealNode, tv } from "./tree.js";

// --- search by name ----------------------------------------------------------------------------
export const SEARCH_SHOWN = 50;
export const search = { matches: [], active: -1 };

export function allShapes() {
  const r = state.result;
  if (!r) return [];
  const out = [{ id: r.root_shape_id, name: nameOf(r.root_shape_id), where: "model" }];
  for (const s of r.subjects) {
    const where = isAttached(s) ? `layer ${s.layer}${isLeaf(s) ? " · leaf" : ""}` : "unattached";
    out.push({ id: s.shape_id, name: s.name || `#${s.shape_id}`, where });
  }
  return out;
}

export const fold = (text) => text.normalize("NFKC").toLocaleLowerCase();

export function findShapes(query) {
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

export function markMatches(ids) {
  for (const [id, node] of tv.nodes) node.g.classList.toggle("rt-match", ids.has(id));
  for (const chip of $("ui-unattached-list").querySelectorAll("button")) {
    chip.classList.toggle("match", ids.has(Number(chip.dataset.shapeId)));
  }
}

export function highlighted(name, query) {
  const q = fold(query.trim());
  const at = fold(name).indexOf(q);
  // NFKC may change lengths: fall back to the plain name when the fold does not line up
  if (at < 0 || fold(name).length !== name.length) return [name];
  return [name.slice(0, at), el("mark", { text: name.slice(at, at + q.length) }), name.slice(at + q.length)];
}

export function renderMatches(query) {
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

export function onSearchInput() {
  const query = $("ui-tree-search").value;
  search.matches = findShapes(query);
  search.active = search.matches.length ? 0 : -1;
  markMatches(new Set(search.matches.map((m) => m.id)));
  renderMatches(query);
}

export function pickMatch(i) {
  const m = search.matches[i];
  if (!m) return;
  search.active = i;
  const list = $("ui-tree-matches");
  list.hidden = true;
  $("ui-tree-search").setAttribute("aria-expanded", "false");
  openSubject(m.id, { zoom: true });
}

export function clearSearch() {
  const input = $("ui-tree-search");
  input.value = "";
  search.matches = [];
  search.active = -1;
  $("ui-tree-matches").hidden = true;
  input.setAttribute("aria-expanded", "false");
  $("ui-tree-found").textContent = "";
  markMatches(new Set());
}

export function setupSearch() {
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
