// The results page's view of a grouping job (issue 11): which shapes came from one mould.
// An ES module: app.js calls show(job, api, current) when a succeeded job's method is
// "grouping" (api: its fetch helper; current(): whether that job is still the open one), and
// hide() when the job is closed.

import { el, fmtNum } from "./core.js";

const urls = [];


function section() {
  let s = document.getElementById("ui-grouping");
  if (!s) {
    s = el("section", { id: "ui-grouping", class: "grouping", hidden: true });
    document.getElementById("ui-job").append(s);
  }
  return s;
}

function hide() {
  const s = document.getElementById("ui-grouping");
  if (s) { s.hidden = true; s.replaceChildren(); }
  while (urls.length) URL.revokeObjectURL(urls.pop());
}

async function picture(api, path, alt) {
  const img = el("img", { alt, class: "grouping-img" });
  try {
    const blob = await api(path, { as: "blob" });
    const url = URL.createObjectURL(blob);
    urls.push(url);
    img.src = url;
  } catch (e) {
    return el("p", { class: "error", text: `Could not draw ${alt}: ${e.message}` });
  }
  return img;
}

async function show(job, api, current) {
  hide();
  let doc;
  try {
    doc = await api(`/v1/jobs/${job.id}/groups`);
  } catch (e) {
    if (current()) section().replaceChildren(el("p", { class: "error", text: `Could not read the groups: ${e.message}` }));
    return;
  }
  if (!current()) return;
  const s = section();
  s.hidden = false;
  const byId = new Map(doc.instances.map((i) => [i.shape_id, i]));
  const compare = el("figure", { class: "card" }, el("figcaption", { text: "Click a shape to see it beside its group's representative." }));
  const showInstance = async (sid) => {
    const i = byId.get(sid);
    const img = await picture(api, `/v1/jobs/${job.id}/groups/instances/${sid}.png`, `shape ${sid} beside its representative`);
    if (!current()) return;
    compare.replaceChildren(el("figcaption", {
      text: `${i.name || "#" + sid}: group ${i.label}, confidence ${i.confidence.toFixed(2)}, distance to the representative ${fmtNum(i.distance_to_representative)}`,
    }), img);
  };
  const rows = doc.groups.map((g) => el("tr", {},
    el("td", { class: "num", text: String(g.label) }),
    el("td", { class: "num", text: String(g.size) }),
    el("td", { text: byId.get(g.representative_shape_id).name || `#${g.representative_shape_id}` }),
    el("td", { class: "num", text: fmtNum(g.spread) }),
    el("td", {}, ...g.shape_ids.map((sid) => el("button", {
      type: "button", class: "chip", title: `confidence ${byId.get(sid).confidence.toFixed(2)}`,
      text: byId.get(sid).name || `#${sid}`, onclick: () => showInstance(sid),
    }))),
  ));
  s.replaceChildren(
    el("h2", { text: `${doc.n_groups} groups of ${doc.shape_ids.length} shapes` }),
    el("p", { class: "hint", text: `threshold ${doc.threshold.toPrecision(3)} (${doc.threshold_source}); noise level ${doc.noise_level.toPrecision(3)}; distances in units of the shapes' RMS radius` }),
    el("table", { class: "subjects" },
      el("thead", {}, el("tr", {}, ...["group", "shapes", "representative", "spread", "members"].map((t) => el("th", { text: t })))),
      el("tbody", {}, ...rows)),
    compare,
  );
  const gallery = await picture(api, `/v1/jobs/${job.id}/groups/gallery.png`, "the groups");
  if (!current()) return;
  s.append(el("figure", { class: "card" }, el("figcaption", { text: "Groups (representative framed in red)" }), gallery));
  const tree = await picture(api, `/v1/jobs/${job.id}/groups/dendrogram.png`, "the dendrogram");
  if (!current()) return;
  s.append(el("figure", { class: "card" }, el("figcaption", { text: "Dendrogram (average linkage) and the cut" }), tree));
}

export { show, hide };
