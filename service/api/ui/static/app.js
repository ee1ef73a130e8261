// dsareg review page: list of jobs -> one job -> approve / reject. Plain JavaScript, no build step,
// nothing loaded from outside this service. The API key stays in sessionStorage (this tab only) and
// goes out as "Authorization: Bearer"; images are fetched with it and shown through object URLs.
import { LAYERS, addView, draw, nativeComposite, resetView, viewsState, zoomBy } from "./views2d.js";

const KEY = "dsareg.apiKey";
const VERDICT_WORDS = {
  ok: "ok: the model matches both views; a look is still advised before use.",
  check: "check: something is doubtful (see the reasons); look at the overlays before using the pose.",
  failed: "failed: the registration did not find a credible pose; do not use it.",
};
let objectUrls = [];
let blinkTimer = null;
let keyHandler = null;
let currentPage = 0;  // which page load is current: a response for an older one is dropped, never appended

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (name.startsWith("on")) node.addEventListener(name.slice(2), value);
    else node.setAttribute(name, value === true ? "" : String(value));
  }
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

function headers(extra) {
  const key = sessionStorage.getItem(KEY);
  return Object.assign(key ? { Authorization: "Bearer " + key } : {}, extra || {});
}

function showKeyForm(needed) {
  // a request without a key answered other than 401: the server has no API keys and the key box nothing to do
  document.getElementById("key-form").hidden = !needed && !sessionStorage.getItem(KEY);
}

async function api(path, options) {
  const response = await fetch(path, Object.assign({}, options, { headers: headers((options || {}).headers) }));
  if (!sessionStorage.getItem(KEY)) showKeyForm(response.status === 401);
  const body = (response.headers.get("content-type") || "").includes("json") ? await response.json() : null;
  if (!response.ok) {
    const detail = body && (body.detail || body.title) ? body.detail || body.title : response.statusText;
    throw new Error(`${response.status}: ${detail}`);
  }
  return body;
}

async function image(path) {
  const response = await fetch(path, { headers: headers() });
  if (!response.ok) throw new Error(`${path}: ${response.status}`);
  const url = URL.createObjectURL(await response.blob());
  objectUrls.push(url);
  return url;
}

function say(text, isError) {
  const message = document.getElementById("message");
  message.textContent = text || "";
  message.className = isError ? "error" : "";
}

function badge(text, kind) {
  if (!text) return el("span", { class: "muted" }, "—");
  return el("span", { class: "badge " + String(kind || text).split(" ")[0] }, text);
}

function reviewBadge(review) {
  return review ? badge(review.decision) : badge("not reviewed", "none");
}

function clearView() {
  currentPage += 1;
  objectUrls.forEach((url) => URL.revokeObjectURL(url));
  objectUrls = [];
  if (blinkTimer) clearInterval(blinkTimer);
  blinkTimer = null;
  if (keyHandler) document.removeEventListener("keydown", keyHandler);
  keyHandler = null;
  const view = document.getElementById("view");
  view.replaceChildren();
  return view;
}

// ---- the list ---------------------------------------------------------------------------------

const filters = { verdict: "", status: "", review: "", q: "" };

function select(name, label, choices) {
  const id = "filter-" + name;
  const control = el("select", { id, name, onchange: (e) => { filters[name] = e.target.value; showList(); } },
    choices.map(([value, text]) => el("option", { value, selected: filters[name] === value }, text)));
  return el("label", { for: id }, label, control);
}

function searchBox() {
  // the search text goes in the API request only: never into the page's own URL (the hash), never logged
  const input = el("input", { id: "search", type: "search", maxlength: 64, value: filters.q, spellcheck: "false",
    placeholder: "patient ID, name, study" });
  const form = el("form", { class: "search", role: "search", onsubmit: (e) => {
    e.preventDefault(); filters.q = input.value.trim(); showList(); } },
  el("label", { for: "search" }, "Search"), input, el("button", { type: "submit" }, "Search"));
  return form;
}

// a header value: one text, or a list of texts when the header holds several values (shown "A; B", never raw)
const shown = (value) => (Array.isArray(value) ? value.join("; ") : value);

function casePatient(c) {
  if (!c) return el("span", { class: "muted" }, "—");
  const who = [shown(c.patient_name), c.patient_id ? `(${shown(c.patient_id)})` : null].filter(Boolean).join(" ");
  return who || el("span", { class: "muted" }, c.source === "upload" ? "upload, no DICOM patient" : "—");
}

function caseStudy(c) {
  if (!c) return el("span", { class: "muted" }, "—");
  return [shown(c.study_date), shown(c.study_description)].filter(Boolean).join(" · ") || el("span", { class: "muted" }, "—");
}

function jobRow(job) {
  const dice = job.dice ? Object.entries(job.dice).map(([v, d]) => `${v} ${d.toFixed(3)}`).join(", ") : "";
  return el("tr", {},
    el("td", { class: "id" }, el("a", { href: "#/job/" + job.id }, job.id.slice(0, 12))),
    el("td", { class: "patient" }, casePatient(job.case)),
    el("td", { class: "study" }, caseStudy(job.case)),
    el("td", {}, (job.created_at || "").replace("T", " ").slice(0, 19)),
    el("td", {}, badge(job.status)),
    el("td", {}, badge(job.verdict)),
    el("td", {}, dice),
    el("td", {}, reviewBadge(job.review)));
}

async function showList() {
  const view = clearView();
  const mine = currentPage;
  document.title = "Jobs · dsareg review";
  view.append(el("h2", {}, "Registration jobs"), el("div", { class: "filters" },
    select("verdict", "Verdict", [["", "any"], ["ok", "ok"], ["check", "check"], ["failed", "failed"]]),
    select("status", "Status", [["", "any"], ["succeeded", "succeeded"], ["failed", "failed"], ["running", "running"],
      ["queued", "queued"], ["canceled", "canceled"]]),
    select("review", "Review", [["", "any"], ["none", "not reviewed"], ["approved", "approved"], ["rejected", "rejected"]]),
    el("button", { type: "button", onclick: showList }, "Refresh")), searchBox());
  const query = new URLSearchParams({ limit: "100" });
  if (filters.status) query.set("status", filters.status);
  if (filters.review) query.set("review", filters.review);
  if (filters.q) query.set("q", filters.q);
  try {
    const page = await api("/v1/registrations?" + query);
    if (mine !== currentPage) return;  // the key, a filter or the search changed while this list was loading
    const items = page.items.filter((job) => !filters.verdict || job.verdict === filters.verdict);
    say(`${items.length} job${items.length === 1 ? "" : "s"}` + (page.next_cursor ? " (newest 100 only)" : ""));
    view.append(el("table", { id: "jobs" },
      el("caption", { class: "muted" }, "Newest first. Open a job to look at it and review it."),
      el("thead", {}, el("tr", {}, ["Job", "Patient", "Study", "Created (UTC)", "Status", "Verdict", "Dice", "Review"].map(
        (h) => el("th", { scope: "col" }, h)))),
      el("tbody", {}, items.map(jobRow))));
  } catch (error) {
    if (mine !== currentPage) return;
    say("Could not load the jobs: " + error.message + (String(error.message).startsWith("401") ? " — enter an API key above." : ""), true);
  }
}

// ---- one job ----------------------------------------------------------------------------------

const SOURCE_WORDS = { upload: "uploaded files", dicomweb: "fetched by DICOMweb", dimse: "received over DIMSE" };

// ---- which run each view's image is from: a tracking job sent one plane carries the other plane's image ----------

function imageOrigins(job) {
  // view -> the id of the earlier job whose run its image is (null: this job's own run)
  const views = (job.result || {}).views || {};
  const inputs = (job.case || {}).inputs || [];
  return Object.fromEntries(["ap", "lat"].map((v) => {
    const row = inputs.find((i) => i.role === v) || {};
    return [v, (views[v] || {}).image_from_job || row.carried_from || null];
  }));
}

function jobLink(id) {
  return el("a", { href: "#/job/" + id, class: "job-link" }, el("code", {}, id.slice(0, 12)));
}

function viewCaption(v, origins, what) {
  // the figure caption of view v: what is shown, and for a tracking job sent one plane, which run each image is
  const name = v.toUpperCase();
  if (origins[v]) return [`${name}: ${what} — the image of an earlier run (job `, jobLink(origins[v]),
    "), carried along: not re-acquired for this job, not fitted"];
  const otherCarried = Object.entries(origins).some(([other, id]) => other !== v && id);
  return `${name}: ${what}` + (otherCarried ? " — acquired for this job (fitted)" : "");
}

function carriedNote(origins) {
  const carried = Object.entries(origins).filter(([, id]) => id);
  if (!carried.length) return null;
  const fresh = Object.keys(origins).filter((v) => !origins[v]).map((v) => v.toUpperCase());
  return el("p", { class: "notice", id: "carried-note", role: "note" },
    fresh.length ? `Only ${fresh.join(" and ")} was acquired for this job (a single-plane tracking run). ` : "",
    carried.map(([v, id], index) => [index ? " " : "", `The ${v.toUpperCase()} image is not from this run: it is job `,
      jobLink(id), `'s, carried along; its outlines show this job's pose on that earlier image, and it was not fitted.`]));
}

function caseSection(job) {
  // whose case: every value is untrusted header text, so only ever text nodes (el() never parses markup)
  const c = job.case;
  if (!c) return el("section", { id: "case", class: "case" }, el("p", { class: "muted" }, "Case: not known yet (the inputs have not been read)."));
  const rows = [["Patient", casePatient(c)], ["Study", caseStudy(c)], ["Accession", shown(c.accession_number)],
    ["Source", SOURCE_WORDS[c.source] || c.source]].filter(([, v]) => v);
  const inputs = (c.inputs || []).map((i) => el("li", { "data-role": i.role }, el("strong", {}, i.role.toUpperCase()), ": ",
    [shown(i.modality), i.series_number ? `series ${shown(i.series_number)}` : null, shown(i.series_description),
      i.instances > 1 ? `${i.instances} instances` : null, i.file_names.length ? i.file_names.join(", ") : null]
      .filter(Boolean).join(" · ") || "—",
    i.carried_from ? [" · carried from an earlier run, job ", jobLink(i.carried_from), " (not re-acquired)"] : null));
  return el("section", { id: "case", class: "case", "aria-label": "Case" },
    el("dl", { class: "case-facts" }, rows.map(([k, v]) => [el("dt", {}, k), el("dd", { "data-field": k.toLowerCase() }, v)])),
    inputs.length ? el("ul", { class: "case-inputs" }, inputs) : null,
    c.mismatch && c.mismatch.length ? el("p", { class: "error", role: "alert" },
      "The inputs disagree on " + c.mismatch.join(", ").replaceAll("_", " ") + ": they may not be one patient's study.") : null);
}

function rotationDeg(m) {
  const trace = m[0][0] + m[1][1] + m[2][2];
  return (Math.acos(Math.max(-1, Math.min(1, (trace - 1) / 2))) * 180) / Math.PI;
}

function metricsList(job) {
  const result = job.result || {};
  const metrics = result.metrics || {};
  const rows = [];
  for (const [name, v] of Object.entries(result.views || {})) {
    if (typeof v.dice === "number") rows.push([`Dice ${name}`, v.dice.toFixed(3)]);
  }
  const pose = result.mesh_to_world;
  if (pose) {
    // the registered pose itself (model frame → C-arm frame), not an error: a model in scanner coordinates turns
    // by any angle to face the C-arm
    rows.push(["Pose translation, model → C-arm (mm; the pose, not an error)",
      [pose[0][3], pose[1][3], pose[2][3]].map((x) => x.toFixed(1)).join(", ")]);
    rows.push(["Pose rotation, model → C-arm (deg; the pose, not an error)", rotationDeg(pose).toFixed(2)]);
  }
  if (typeof metrics.loss === "number") rows.push(["Final loss", metrics.loss.toPrecision(3)]);
  if (metrics.reason) rows.push(["Optimizer stopped", metrics.reason]);
  if (job.started_at && job.finished_at) {
    rows.push(["Run time (s)", ((Date.parse(job.finished_at) - Date.parse(job.started_at)) / 1000).toFixed(1)]);
  }
  return el("dl", { class: "metrics" }, rows.map(([k, v]) => [el("dt", {}, k), el("dd", {}, v)]));
}

function verdictSection(job) {
  const confidence = ((job.result || {}).metrics || {}).confidence || {};
  const reasons = confidence.reasons || [];
  const words = VERDICT_WORDS[confidence.verdict] || (job.error ? "The job failed: " + job.error.detail : "No verdict.");
  return el("section", { "aria-labelledby": "verdict-h" }, el("h3", { id: "verdict-h" }, "Verdict ", badge(confidence.verdict)),
    el("p", {}, words),
    reasons.length ? el("ul", { class: "reasons" }, reasons.map((r) => el("li", {}, r))) : null,
    job.warnings && job.warnings.length ? [el("h3", {}, "Warnings"),
      el("ul", { class: "warnings" }, job.warnings.map((w) => el("li", {}, w)))] : null);
}

function overlayViews(job) {
  // jobs of earlier versions (no image / layers files): the overlays as exported
  const links = job.links;
  const views = ["ap", "lat"].filter((v) => links["overlay_" + v]);
  if (!views.length) return null;
  const origins = imageOrigins(job);
  const figures = views.map((v) => {
    const img = el("img", { alt: `${v.toUpperCase()} view: overlay of the registered model on the DSA`, "data-view": v });
    const caption = el("figcaption", { "data-view": v }, viewCaption(v, origins, "overlay"));
    return { v, img, caption, figure: el("figure", {}, img, caption), urls: {} };
  });
  let showing = "overlay";
  const show = (kind) => {
    showing = kind;
    for (const f of figures) {
      if (f.urls[kind]) f.img.src = f.urls[kind];
      f.img.alt = `${f.v.toUpperCase()} view: ` + (kind === "overlay" ? "overlay of the registered model on the DSA" : "vessel mask used for the registration");
      f.caption.replaceChildren(...[viewCaption(f.v, origins, kind === "overlay" ? "overlay" : "vessel mask")].flat());
    }
    toggle.setAttribute("aria-pressed", kind === "mask" ? "true" : "false");
  };
  const toggle = el("button", { type: "button", id: "toggle-masks", "aria-pressed": "false",
    onclick: () => show(showing === "overlay" ? "mask" : "overlay") }, "Show masks");
  const blink = el("button", { type: "button", id: "blink", "aria-pressed": "false", onclick: () => {
    if (blinkTimer) { clearInterval(blinkTimer); blinkTimer = null; blink.setAttribute("aria-pressed", "false"); show("overlay"); return; }
    blink.setAttribute("aria-pressed", "true");
    blinkTimer = setInterval(() => show(showing === "overlay" ? "mask" : "overlay"), 700);
  } }, "Blink");
  for (const f of figures) {
    image(links["overlay_" + f.v]).then((url) => { f.urls.overlay = url; if (showing === "overlay") f.img.src = url; })
      .catch((e) => say(e.message, true));
    if (links["mask_" + f.v]) image(links["mask_" + f.v]).then((url) => { f.urls.mask = url; }).catch(() => {});
  }
  return el("section", { "aria-labelledby": "views-h" }, el("h3", { id: "views-h" }, "Views"), carriedNote(origins),
    el("div", { class: "toolbar" }, toggle, blink), el("div", { class: "views" }, figures.map((f) => f.figure)));
}

// ---- the workspace: image registered + layers, zoom / pan at one mm scale, 3D scene ---------------

function viewsSection(job) {
  const links = job.links;
  const views = ["ap", "lat"].filter((v) => links["image_" + v] && links["layers_" + v]);
  if (!views.length || !links.model) return overlayViews(job);
  const state = viewsState();
  const model = api(links.model);
  const origins = imageOrigins(job);
  const figures = views.map((v) => {
    const earlier = origins[v] ? ` (an earlier run's image, job ${origins[v].slice(0, 12)}, carried along, not fitted)` : "";
    const canvas = el("canvas", { width: 400, height: 400, tabindex: 0, class: "view2d", "data-view": v,
      "aria-label": `${v.toUpperCase()} view: the image registered${earlier} under the outlines; drag to pan, wheel or + and - to zoom` });
    return { v, canvas, figure: el("figure", {}, canvas,
      el("figcaption", { "data-view": v }, viewCaption(v, origins, "the image registered"))) };
  });
  const scale = el("span", { class: "scalebar", id: "scalebar" });
  const scaleText = el("span", { id: "scale-text" });
  state.onDraw = (pxPerMm) => {
    drawScaleBar(scale, scaleText, pxPerMm);
    section.dataset.pxPerMm = pxPerMm.toFixed(4); // screen px per mm at the model, the same in both views
  };
  const toggles = LAYERS.map((layer) => {
    const swatch = el("span", { class: "swatch", "aria-hidden": "true" });
    swatch.style.backgroundColor = `rgba(${layer.rgba.slice(0, 3).join(",")},${layer.rgba[3] / 255})`;
    const button = el("button", { type: "button", id: "toggle-" + layer.key, "aria-pressed": String(layer.on), onclick: () => {
      state.shown[layer.key] = !state.shown[layer.key];
      button.setAttribute("aria-pressed", String(state.shown[layer.key]));
      draw(state);
      if (state.onLayers) state.onLayers();
    } }, swatch, layer.label);
    return button;
  });
  const section = el("section", { "aria-labelledby": "views-h", id: "views" }, el("h3", { id: "views-h" }, "Views"),
    carriedNote(origins),
    el("div", { class: "toolbar", role: "group", "aria-label": "Layers (the legend)" }, toggles),
    el("div", { class: "toolbar", role: "group", "aria-label": "Zoom" },
      el("button", { type: "button", id: "zoom-in", onclick: () => zoomBy(state, 1.25) }, "Zoom in"),
      el("button", { type: "button", id: "zoom-out", onclick: () => zoomBy(state, 0.8) }, "Zoom out"),
      el("button", { type: "button", id: "zoom-fit", onclick: () => resetView(state) }, "Fit"),
      el("span", { class: "scale" }, scale, scaleText)),
    el("div", { class: "views" }, figures.map((f) => f.figure)),
    el("p", { class: "muted small" }, "Both views at one scale: a millimetre at the model's depth is as long in each. " +
      "Drag to pan a view; the wheel or + and − (on a focused view) zoom both."));
  state.ready = model.then(async (doc) => {
    await Promise.all(figures.map(async (f) => {
      const [imageUrl, layersUrl] = await Promise.all([image(links["image_" + f.v]), image(links["layers_" + f.v])]);
      const detector = (doc.views || {})[f.v] || {};
      await addView(state, f.v, f.canvas, imageUrl, layersUrl, detector.mm_per_px_at_model || (detector.pixel_spacing_mm || [1])[0]);
    }));
    state.views.sort((a, b) => a.name.localeCompare(b.name));
    for (const f of figures) { f.canvas.width = f.canvas.clientWidth || 400; f.canvas.height = f.canvas.width; }
    draw(state);
    section.dataset.ready = "1";
    return doc;
  }).catch((e) => { say("The views could not be shown: " + e.message, true); throw e; });
  section.append(scene3dSection(job, state));
  return section;
}

function drawScaleBar(bar, text, pxPerMm) {
  const mm = [1, 2, 5, 10, 20, 50, 100].find((m) => m * pxPerMm >= 60) || 100;
  bar.style.width = `${Math.round(mm * pxPerMm)}px`;
  text.textContent = ` ${mm} mm at the model`;
}

function scene3dSection(job, state) {
  const canvas = el("canvas", { id: "scene3d", class: "scene3d", tabindex: 0,
    "aria-label": "3D scene: the model in the registered pose, both X-ray sources and detectors; drag to orbit, wheel to zoom" });
  const ghost = el("button", { type: "button", id: "toggle-ghost", "aria-pressed": "true" }, "Initial pose (ghost)");
  const frameModel = el("button", { type: "button", id: "frame-model" }, "Frame the model");
  const frameRig = el("button", { type: "button", id: "frame-rig" }, "Frame the C-arm");
  const note = el("p", { class: "muted small", id: "scene-note" }, "Orange: the model in the registered pose; grey: the initial pose; " +
    "blue: the AP source and its beam, green: the LAT; each detector shows its view with the layers on.");
  const section = el("section", { "aria-labelledby": "scene-h", id: "scene" }, el("h3", { id: "scene-h" }, "3D scene"),
    el("div", { class: "toolbar" }, ghost, frameModel, frameRig), canvas, note);
  state.ready.then(async (model) => {
    const arrival = await arrivalOf(job, model, note);
    const { showScene } = await import("./scene3d.js");
    const textures = Object.fromEntries(state.views.map((v) => [v.name, nativeComposite(state, v)]));
    const scene = await showScene(canvas, model, textures, arrival);
    frameModel.addEventListener("click", () => scene.frame(false));
    frameRig.addEventListener("click", () => scene.frame(true));
    ghost.addEventListener("click", () => {
      scene.ghost.visible = !scene.ghost.visible;
      ghost.setAttribute("aria-pressed", String(scene.ghost.visible));
      scene.render();
    });
    state.onLayers = () => state.views.forEach((v) => scene.setTexture(v.name, nativeComposite(state, v)));
    section.dataset.ready = "1";
  }).catch((e) => note.replaceChildren(el("span", { class: "error" }, "The 3D scene could not be shown: " + e.message)));
  return section;
}

async function arrivalOf(job, model, note) {
  // hemodynamics.json: arrival_s per vertex of the model file as given, the same order as model.json
  if (!job.links.hemodynamics) return null;
  const doc = await api(job.links.hemodynamics);
  const arrival = doc && doc.arrival_s;
  if (!arrival || arrival.length !== model.vertex_count) {
    note.append(el("br"), "Arrival times not shown: they do not match the model's vertices.");
    return null;
  }
  const known = arrival.filter((t) => t !== null);
  note.replaceChildren(`Coloured by contrast arrival: blue ${Math.min(...known).toFixed(2)} s → yellow → red ` +
    `${Math.max(...known).toFixed(2)} s after the first AP frame; grey: never filled. Grey ghost: the initial pose.`);
  return arrival;
}

function plotFigure(link, alt, caption) {
  if (!link) return null;
  const img = el("img", { alt });
  image(link).then((url) => { img.src = url; }).catch(() => {});
  return el("figure", { class: "plot" }, img, el("figcaption", {}, caption));
}

function reviewSection(job) {
  const finished = !["queued", "running"].includes(job.status);
  const current = job.review
    ? el("p", { id: "review-state" }, "Reviewed: ", reviewBadge(job.review), ` by ${job.review.by} at ${job.review.at.replace("T", " ").slice(0, 19)}`,
      job.review.comment ? el("br") : null, job.review.comment ? `“${job.review.comment}”` : null)
    : el("p", { id: "review-state" }, reviewBadge(null));
  const comment = el("textarea", { id: "comment", name: "comment", maxlength: 2000, disabled: !finished });
  const send = async (decision) => {
    try {
      const updated = await api(`/v1/registrations/${job.id}/review`, { method: "POST",
        headers: { "Content-Type": "application/json" }, body: JSON.stringify({ decision, comment: comment.value }) });
      say(`Saved: ${decision}.`);
      document.getElementById("review-state").replaceWith(reviewSection(updated).querySelector("#review-state"));
      const shown = document.getElementById("export-state");
      if (shown && updated.export) shown.replaceWith(exportState(updated.export));
      document.getElementById("history").replaceWith(historySection(updated).querySelector("#history"));
      if (updated.export && ["pending", "exporting"].includes(updated.export.state)) watchExport(job.id, 30);
    } catch (error) { say("The review was not saved: " + error.message, true); }
  };
  const section = el("section", { "aria-labelledby": "review-h", class: "review-form" }, el("h3", { id: "review-h" }, "Review"), current,
    finished ? null : el("p", { class: "muted" }, "The job has not finished; it can be reviewed once it has."),
    finished ? el("p", { class: "muted small", id: "review-keys" }, "Keyboard: A approve, R reject, then Y to confirm.") : null,
    el("p", { id: "review-prompt", role: "alert" }),
    el("label", { for: "comment" }, "Comment (optional, at most 2000 characters)"), comment,
    el("div", { class: "actions" },
      el("button", { type: "button", class: "approve", id: "approve", disabled: !finished, onclick: () => send("approved") }, "Approve"),
      el("button", { type: "button", class: "reject", id: "reject", disabled: !finished, onclick: () => send("rejected") }, "Reject")));
  section.send = finished ? send : null;
  return section;
}

function reviewKeys(send) {
  // A or R asks, Y confirms (any other key cancels); never while typing in a field
  let pending = null;
  return (event) => {
    const target = event.target;
    if (event.altKey || event.ctrlKey || event.metaKey || ["INPUT", "TEXTAREA", "SELECT"].includes(target.tagName)) return;
    const prompt = document.getElementById("review-prompt");
    const key = event.key.toLowerCase();
    if (pending && key === "y") {
      const decision = pending;
      pending = null;
      prompt.textContent = "";
      send(decision);
    } else if (key === "a" || key === "r") {
      pending = key === "a" ? "approved" : "rejected";
      prompt.textContent = `${key === "a" ? "Approve" : "Reject"} this job? Press Y to confirm, any other key to cancel.`;
    } else if (pending) {
      pending = null;
      prompt.textContent = "Not saved.";
    } else return;
    event.preventDefault();
  };
}

const EXPORT_WORDS = {
  awaiting_review: "held until the job is approved",
  pending: "queued; being sent",
  exporting: "being sent",
  done: "stored",
  failed: "failed",
  skipped: "not sent (rejected)",
};

function exportLine(job) {
  // the export state and destination, always: held for review, stored at once, or nothing to store
  if (job.export) return exportState(job.export);
  const dicom = (job.result || {}).dicom || {};
  if (dicom.stored) {
    return el("p", { id: "export-state" }, "PACS export: ", badge(dicom.stored.confirmed ? "stored" : "sent", "ok"),
      ` (STOW-RS to ${dicom.stored.server}, ${dicom.stored.sop_instance_uids.length} objects, when the job ended)`);
  }
  if (dicom.exported) {
    const done = dicom.exported.filter((e) => e.status === "stored").length;
    return el("p", { id: "export-state" }, "PACS export: ", badge(done === dicom.exported.length ? "stored" : "failed", done === dicom.exported.length ? "ok" : "failed"),
      ` (C-STORE to ${dicom.exported.map((e) => e.peer || e.ae_title || "?").join(", ")}, when the job ended)`);
  }
  return el("p", { id: "export-state" }, "PACS export: ", badge("none", "none"),
    " (this job stores nothing into a PACS: its results are here and in the API only)");
}

function exportState(exp) {
  if (!exp) return null;
  // sent by the service after the job succeeded (the job itself never waits on the PACS)
  const where = `${exp.via === "stow-rs" ? "STOW-RS" : "C-STORE"} to ${exp.destination}`;
  const retrying = exp.state === "pending" && exp.attempts > 0;
  const word = retrying ? "retrying" : exp.state === "pending" && exp.after_review ? "approved; being sent" : EXPORT_WORDS[exp.state] || exp.state;
  const next = retrying && exp.next_attempt_at ? `, next at ${exp.next_attempt_at.replace("T", " ").slice(0, 19)}` : "";
  return el("p", { id: "export-state" }, "PACS export: ", badge(word, exp.state === "done" ? "ok" : exp.state),
    ` (${where}${exp.attempts ? `, ${exp.attempts} attempt${exp.attempts === 1 ? "" : "s"}` : ""}${next})`,
    exp.error && exp.state !== "done" ? [el("br"), el("span", { class: "error" }, exp.error.detail || exp.error.title)] : null);
}

async function watchExport(id, polls) {
  // the export runs in the service after the job (or the approval): follow it for a while (every 1 s)
  await new Promise((done) => setTimeout(done, 1000));
  const shown = document.getElementById("export-state");
  if (!shown || !location.hash.endsWith(id)) return;
  let job;
  try { job = await api("/v1/registrations/" + encodeURIComponent(id)); } catch (error) { return; }
  if (!job.export) return;
  shown.replaceWith(exportState(job.export));
  if (["pending", "exporting"].includes(job.export.state) && polls > 1) { watchExport(id, polls - 1); return; }
  document.getElementById("history").replaceWith(historySection(job).querySelector("#history"));
}

function historySection(job) {
  const list = el("ol", { class: "history", id: "history" });
  api(`/v1/registrations/${job.id}/audit`).then((log) => {
    list.replaceChildren(...log.items.map((item) => {
      const details = item.details || {};
      const note = item.event === "reviewed" ? `${details.decision}${details.comment ? ` “${details.comment}”` : ""}`
        : details.detail || (details.via ? `${details.via} ${details.server || (details.peers || []).join(", ") || ""}` : "");
      return el("li", {}, el("time", { datetime: item.at }, item.at.replace("T", " ").slice(0, 19)), " ",
        el("strong", {}, item.event.replaceAll("_", " ")), " · ", item.actor, note ? ` · ${note}` : "");
    }));
  }).catch((error) => list.replaceChildren(el("li", { class: "error" }, "Could not load the history: " + error.message)));
  return el("section", { "aria-labelledby": "history-h" }, el("h3", { id: "history-h" }, "History"), list);
}

async function showJob(id) {
  const view = clearView();
  const mine = currentPage;
  let job;
  try { job = await api("/v1/registrations/" + encodeURIComponent(id)); } catch (error) {
    if (mine !== currentPage) return;
    view.append(el("p", {}, el("a", { href: "#/" }, "← All jobs")));
    say("Could not load the job: " + error.message, true);
    return;
  }
  if (mine !== currentPage) return;  // another page was asked for while this job was loading
  say("");
  document.title = `Job ${id.slice(0, 8)} · dsareg review`;
  const review = reviewSection(job);
  if (review.send) {
    keyHandler = reviewKeys(review.send);
    document.addEventListener("keydown", keyHandler);
  }
  view.append(el("p", {}, el("a", { href: "#/" }, "← All jobs")),
    el("h2", {}, "Job ", el("code", {}, id), " ", badge(job.status)), caseSection(job),
    el("div", { class: "job" },
      el("div", {}, viewsSection(job), el("div", { class: "plots" },
        plotFigure(job.links.loss_plot, "Loss per iteration of the registration", "Loss per iteration"),
        plotFigure(job.links.animation, "Animation of the registration converging", "Animation"))),
      el("div", {}, review, exportLine(job), verdictSection(job), el("h3", {}, "Metrics"),
        metricsList(job), historySection(job))));
  if (job.export && ["pending", "exporting"].includes(job.export.state)) watchExport(id, 60);
}

// ---- the key and the router ---------------------------------------------------------------------

function keyState() {
  document.getElementById("key-state").textContent = sessionStorage.getItem(KEY) ? "key set for this tab" : "no key";
}

function route() {
  const match = location.hash.match(/^#\/job\/([A-Za-z0-9_-]{1,64})$/);
  if (match) showJob(match[1]); else showList();
  document.getElementById("main").focus({ preventScroll: true });
}

document.addEventListener("DOMContentLoaded", () => {
  document.getElementById("key-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const input = document.getElementById("api-key");
    if (input.value.trim()) sessionStorage.setItem(KEY, input.value.trim());
    input.value = "";
    keyState();
    route();
  });
  document.getElementById("forget-key").addEventListener("click", () => { sessionStorage.removeItem(KEY); keyState(); route(); });
  keyState();
  if (sessionStorage.getItem(KEY)) showKeyForm(true);  // a key kept from before: its "Forget key" stays reachable
  window.addEventListener("hashchange", route);
  route();
});
