// HKTex dashboard: plain script, no build step. Talks to the same REST API as any client,
// with the bearer token kept in sessionStorage (this tab only, never in a URL). Job progress
// comes over the API's server-sent events, read with fetch() because EventSource cannot send
// an Authorization header. All text from the service goes in through textContent (names of
// uploaded files are strangers' input).
"use strict";

const TOKEN_KEY = "hktex.token";
const CURVES_KEY = "hktex.curves";
const ACTIVE = ["queued", "running", "cancelling"];
const SPECTRA_FIELDS = ["angles", "anisotropies", "k", "k_iso", "rotation", "evecs_dtype", "tangent_field"];
const BAKE_RESOLUTION = 512;
const REFRESH_MS = 3000;

const S = {
  token: sessionStorage.getItem(TOKEN_KEY),
  owner: null,
  data: { meshes: [], jobs: [], kernelsets: [], spectra: [] },
  shown: {},            // last rendered JSON per table: re-render only on change
  streams: new Map(),   // job id -> AbortController
  curves: JSON.parse(sessionStorage.getItem(CURVES_KEY) || "{}"),
  viewer: { id: null, layers: {}, textures: {}, bake: null },
  timer: null,
};

const $ = (id) => document.getElementById(id);

class AuthError extends Error {}
class ApiError extends Error {
  constructor(status, detail) { super(`${status}: ${detail}`); this.status = status; this.detail = detail; }
}

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v;
    else if (k === "onclick") node.addEventListener("click", v);
    else if (k.startsWith("data-")) node.setAttribute(k, v);
    else node[k] = v;
  }
  for (const c of children) node.append(c instanceof Node ? c : document.createTextNode(c ?? ""));
  return node;
}

function say(id, text, kind = "") {
  const node = $(id);
  node.textContent = text;
  node.className = `msg ${kind}`;
}

async function api(path, opts = {}) {
  const headers = { ...(opts.headers || {}) };
  if (S.token) headers.Authorization = `Bearer ${S.token}`;
  const r = await fetch(path, { ...opts, headers });
  if (r.ok) return r;
  let detail = r.statusText;
  try { const body = await r.json(); detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail); } catch (_) { /* not JSON */ }
  if (r.status === 401) throw new AuthError(detail);
  throw new ApiError(r.status, detail);
}
const getJSON = async (path, opts) => (await api(path, opts)).json();
async function blobURL(path) { return URL.createObjectURL(await (await api(path)).blob()); }

// ------------------------------------------------------------------ sign in / out

async function signIn(token) {
  S.token = token || null;
  let info;
  try {
    info = await getJSON("/v1/info");
  } catch (e) {
    S.token = null;
    sessionStorage.removeItem(TOKEN_KEY);
    if (e instanceof AuthError) {
      showLogin(token ? `The service refused this token (${e.message}). Check it and try again.` : "");
    } else {
      showLogin(`The service did not answer: ${e.message}`);
    }
    return;
  }
  if (S.token) sessionStorage.setItem(TOKEN_KEY, S.token);
  S.owner = info.owner;
  $("owner").textContent = info.owner;
  $("signout").hidden = !S.token; // a service without tokens has nobody to sign out
  $("service-info").textContent = `hktex ${info.version} · ${info.workers} worker slot(s) · ` +
    `queue ${info.queue.queued} queued, ${info.queue.running} running`;
  $("login").hidden = true;
  $("app").hidden = false;
  $("whoami").hidden = false;
  await refresh();
  clearInterval(S.timer);
  S.timer = setInterval(() => refresh().catch(() => {}), REFRESH_MS);
}

function showLogin(message) {
  clearInterval(S.timer);
  for (const ctl of S.streams.values()) ctl.abort();
  S.streams.clear();
  S.shown = {};
  $("app").hidden = true;
  $("whoami").hidden = true;
  $("login").hidden = false;
  say("login-msg", message, message ? "error" : "");
  $("token").value = "";
  $("token").focus();
}

function signOut() {
  sessionStorage.removeItem(TOKEN_KEY);
  S.token = null;
  showLogin("Signed out.");
  $("login-msg").className = "msg ok";
}

function guard(fn) {
  // every action: a revoked token sends the user back to the sign-in form with the reason
  return async (...args) => {
    try { return await fn(...args); } catch (e) {
      if (e instanceof AuthError) { showLogin(`Your token is no longer accepted (${e.message}).`); return; }
      throw e;
    }
  };
}

// ------------------------------------------------------------------ lists

const refresh = guard(async () => {
  const [meshes, jobs, kernelsets, spectra, info] = await Promise.all([
    getJSON("/v1/meshes"), getJSON("/v1/jobs?limit=100"), getJSON("/v1/kernelsets?limit=100"),
    getJSON("/v1/spectra?limit=100"), getJSON("/v1/info"),
  ]);
  S.data = { meshes: meshes.items, jobs: jobs.items, kernelsets: kernelsets.items, spectra: spectra.items };
  $("service-info").textContent = `hktex ${info.version} · ${info.workers} worker slot(s) · ` +
    `queue ${info.queue.queued} queued, ${info.queue.running} running`;
  renderAll();
  for (const job of S.data.jobs) if (ACTIVE.includes(job.state)) follow(job.id);
});

function renderAll() {
  renderTable("meshes", S.data.meshes, meshRow);
  renderTable("jobs", S.data.jobs, jobRow);
  renderTable("kernelsets", S.data.kernelsets, kernelsetRow);
  renderTable("spectra", S.data.spectra, spectraRow);
  $("jobs-msg").textContent = S.data.jobs.length ? "" : "No jobs yet: upload a mesh with a texture above.";
}

function renderTable(id, items, row) {
  const key = JSON.stringify(items) + (id === "jobs" ? JSON.stringify(S.curves) : "");
  if (S.shown[id] === key) return;
  S.shown[id] = key;
  const body = $(id).querySelector("tbody");
  body.replaceChildren(...items.map(row));
  if (!items.length) body.append(el("tr", {}, el("td", { colSpan: 9, class: "small" }, "none yet")));
}

const meshName = (id) => (S.data.meshes.find((m) => m.id === id) || {}).name || (id ? id.slice(0, 12) : "");
const short = (id) => (id ? id.replace(/^([a-z]+_)(.{8}).*$/, "$1$2") : "");
const bytes = (n) => (n == null ? "" : Number(n).toLocaleString("en-US"));
const when = (t) => (t ? new Date(t * 1000).toLocaleString() : "");
const fmt = (x, d = 4) => (typeof x === "number" ? Number(x.toPrecision(d)).toString() : "");

function meshRow(m) {
  const fit = el("button", { type: "button", onclick: guard(() => startFit(m.id)), disabled: !m.has_texture,
    title: m.has_texture ? "UV fit with the parameters of the form above" : "needs a texture" }, "Fit UV");
  return el("tr", { "data-mesh-id": m.id }, el("td", {}, m.name), el("td", { class: "num" }, bytes(m.n_vertices)),
    el("td", { class: "num" }, bytes(m.n_faces)), el("td", {}, m.has_texture ? "yes" : "no"),
    el("td", { class: "num" }, bytes(m.bytes)), el("td", { class: "small" }, when(m.created_at)), el("td", {}, fit));
}

function jobRow(j) {
  const p = j.progress || {};
  const frac = p.total ? Math.min(1, p.step / p.total) : (j.state === "succeeded" ? 1 : 0);
  const bar = el("span", { class: "bar", title: `${Math.round(100 * frac)}%` }, el("span"));
  bar.firstChild.style.width = `${(100 * frac).toFixed(1)}%`;
  const actions = el("td", {});
  if (ACTIVE.includes(j.state) && !j.cancel_requested) {
    actions.append(el("button", { type: "button", class: "cancel", onclick: guard(() => cancelJob(j.id)) }, "Cancel"));
  }
  if (!ACTIVE.includes(j.state) && j.mesh_id && j.task === "fit_uv") {
    actions.append(el("button", { type: "button", class: "retry", onclick: guard(() => retryJob(j)) }, "Retry"));
  }
  if (j.result && j.result.kernelset_id) {
    actions.append(el("button", { type: "button", class: "view", onclick: guard(() => openViewer(j.result.kernelset_id)) }, "View"));
  }
  const stage = p.stage ? ` ${p.stage}` : "";
  const stateCell = el("td", {}, el("span", { class: `state ${j.state}` }, j.state));
  if (j.error) stateCell.append(el("div", { class: "small", title: j.error }, j.error.slice(0, 80)));
  return el("tr", { "data-job-id": j.id, "data-state": j.state, "data-step": String(p.step || 0) },
    el("td", {}, el("code", { title: j.id }, short(j.id))), el("td", {}, j.task),
    el("td", {}, meshName(j.mesh_id)), stateCell,
    el("td", {}, bar, el("span", { class: "small" }, ` ${p.step || 0}/${p.total || 0}${stage}`)),
    el("td", { class: "num" }, fmt(p.loss)), el("td", { class: "num" }, bytes(p.kernel_count)),
    el("td", {}, sparkline(S.curves[j.id] || [])), actions);
}

function kernelsetRow(k) {
  const m = k.metrics || {};
  const psnr = typeof m.surface_psnr === "number" ? `${m.surface_psnr.toFixed(2)} dB` : "";
  const view = el("button", { type: "button", class: "view", onclick: guard(() => openViewer(k.id)) }, "View 3D");
  const dl = el("button", { type: "button", onclick: guard(() => download(`/v1/kernelsets/${k.id}/file`, `${k.id}.hkt`)) }, ".hkt");
  const glb = el("button", { type: "button", onclick: guard(() => download(`/v1/kernelsets/${k.id}/glb`, `${k.id}.glb`)) }, ".glb");
  return el("tr", { "data-kernelset-id": k.id }, el("td", {}, el("code", { title: k.id }, short(k.id))),
    el("td", {}, meshName(k.mesh_id)), el("td", { class: "num" }, bytes(k.n_kernels)),
    el("td", { class: "num" }, bytes(k.bytes)), el("td", { class: "num" }, bytes(m.bytes_zip)),
    el("td", { class: "num" }, psnr), el("td", { class: "small" }, when(k.created_at)), el("td", {}, view, " ", dl, " ", glb));
}

function spectraRow(s) {
  const c = s.config || {};
  const grid = `${c.angles ?? "?"} angles × [${(c.anisotropies || []).join(", ")}], k ${c.k ?? "?"}`;
  const sum = s.summary || {};
  return el("tr", { "data-spectra-id": s.id }, el("td", {}, el("code", { title: s.id }, short(s.id))),
    el("td", {}, el("span", { class: `state ${s.state === "ready" ? "succeeded" : s.state}` }, s.state)),
    el("td", { class: "small" }, grid), el("td", { class: "num" }, bytes(sum.bytes ?? sum.disk_bytes)),
    el("td", { class: "small" }, when(s.updated_at)));
}

// ------------------------------------------------------------------ loss curves

function remember(job) {
  const p = job.progress || {};
  if (typeof p.loss !== "number" || !p.step) return;
  const pts = (S.curves[job.id] ||= []);
  if (pts.length && pts[pts.length - 1][0] >= p.step) return;
  pts.push([p.step, p.loss]);
  if (pts.length > 400) pts.splice(0, pts.length - 400);
  sessionStorage.setItem(CURVES_KEY, JSON.stringify(S.curves));
}

function curvePath(pts, w, h, pad) {
  const xs = pts.map((p) => p[0]);
  const ys = pts.map((p) => Math.log10(Math.max(p[1], 1e-12)));
  const [x0, x1] = [Math.min(...xs), Math.max(...xs, Math.min(...xs) + 1)];
  let [y0, y1] = [Math.min(...ys), Math.max(...ys)];
  if (y1 - y0 < 1e-9) { y0 -= 0.5; y1 += 0.5; }
  const X = (x) => pad + ((x - x0) / (x1 - x0)) * (w - 2 * pad);
  const Y = (y) => h - pad - ((y - y0) / (y1 - y0)) * (h - 2 * pad);
  return { d: pts.map((p, i) => `${i ? "L" : "M"}${X(p[0]).toFixed(1)},${Y(ys[i]).toFixed(1)}`).join(""), x0, x1, y0, y1 };
}

function svg(tag, attrs) {
  const n = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs)) n.setAttribute(k, v);
  return n;
}

function sparkline(pts) {
  const s = svg("svg", { width: 120, height: 28, viewBox: "0 0 120 28", class: "spark" });
  if (pts.length >= 2) s.append(svg("path", { d: curvePath(pts, 120, 28, 2).d, fill: "none", stroke: "#c2410c", "stroke-width": 1.5 }));
  return s;
}

function drawCurve(node, pts) {
  node.replaceChildren();
  const [w, h, pad] = [512, 300, 40];
  node.append(svg("rect", { x: 0, y: 0, width: w, height: h, fill: "#fff" }));
  if (pts.length < 2) {
    const t = svg("text", { x: w / 2, y: h / 2, "text-anchor": "middle", fill: "#66707c" });
    t.textContent = "no loss samples seen by this tab (curves are recorded while a job runs)";
    t.setAttribute("font-size", "12");
    node.append(t);
    return;
  }
  const c = curvePath(pts, w, h, pad);
  node.append(svg("path", { d: `M${pad},${pad}V${h - pad}H${w - pad}`, fill: "none", stroke: "#9aa3ad" }));
  node.append(svg("path", { d: c.d, fill: "none", stroke: "#c2410c", "stroke-width": 2 }));
  const label = (x, y, text, anchor = "start") => {
    const t = svg("text", { x, y, "text-anchor": anchor, fill: "#434b55", "font-size": 12 });
    t.textContent = text;
    node.append(t);
  };
  label(pad, h - pad + 16, `step ${c.x0}`);
  label(w - pad, h - pad + 16, `step ${c.x1}`, "end");
  label(pad + 4, pad - 8, `loss ${fmt(10 ** c.y1, 3)} (log scale)`);
  label(pad + 4, h - pad - 6, fmt(10 ** c.y0, 3));
}

// The fit's whole curve as its record keeps it (one mean per run of steps); the points this
// tab saw while the job ran are the fallback (a set fitted before curves were recorded).
async function showCurve(id) {
  const ks = S.data.kernelsets.find((k) => k.id === id);
  let pts = [];
  try {
    const rec = await getJSON(`/v1/kernelsets/${id}`);
    const curve = (rec.metrics || {}).loss_curve;
    const finite = (p) => Array.isArray(p) && p.length === 2 && typeof p[1] === "number";
    if (Array.isArray(curve)) pts = curve.filter(finite);  // a diverged step's loss is null
  } catch (e) {
    if (e instanceof AuthError) throw e;
  }
  const source = pts.length >= 2 ? "record" : "tab";
  if (source === "tab") pts = (ks && S.curves[ks.job_id]) || [];
  $("pic-curve").dataset.source = source;
  drawCurve($("pic-curve"), pts);
}

// ------------------------------------------------------------------ live progress (SSE)

async function follow(jobId) {
  if (S.streams.has(jobId)) return;
  const ctl = new AbortController();
  S.streams.set(jobId, ctl);
  try {
    const r = await api(`/v1/jobs/${jobId}/events`, { signal: ctl.signal, headers: { Accept: "text/event-stream" } });
    const reader = r.body.getReader();
    const dec = new TextDecoder();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buf += dec.decode(value, { stream: true }).replace(/\r\n/g, "\n");
      let cut;
      while ((cut = buf.indexOf("\n\n")) >= 0) {
        onEvent(buf.slice(0, cut));
        buf = buf.slice(cut + 2);
      }
    }
  } catch (e) {
    if (e instanceof AuthError) showLogin(`Your token is no longer accepted (${e.message}).`);
  } finally {
    S.streams.delete(jobId);
  }
}

function onEvent(block) {
  let name = "message";
  const data = [];
  for (const line of block.split("\n")) {
    if (line.startsWith("event:")) name = line.slice(6).trim();
    else if (line.startsWith("data:")) data.push(line.slice(5).trimStart());
  }
  if (!data.length) return; // keep-alive comment
  const job = JSON.parse(data.join("\n"));
  remember(job);
  const i = S.data.jobs.findIndex((j) => j.id === job.id);
  if (i >= 0) S.data.jobs[i] = job; else S.data.jobs.unshift(job);
  renderTable("jobs", S.data.jobs, jobRow);
  if (name === "end") refresh().catch(() => {});
}

// ------------------------------------------------------------------ actions

function fitBody(meshId) {
  const num = (id) => ($(id).value.trim() === "" ? undefined : Number($(id).value));
  const params = { kernels: num("kernels"), max_kernels: num("max-kernels"), steps: num("steps") };
  const spectra = { angles: num("angles"), k: num("k"), k_iso: num("k-iso") };
  const an = $("anisotropies").value.trim();
  if (an) spectra.anisotropies = an.split(",").map((a) => Number(a.trim()));
  const clean = (o) => Object.fromEntries(Object.entries(o).filter(([, v]) => v !== undefined));
  return { mesh_id: meshId, task: "fit_uv", params: clean(params), spectra: clean(spectra) };
}

async function startFit(meshId) {
  try {
    const job = await getJSON("/v1/jobs", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(fitBody(meshId)) });
    say("upload-msg", `UV fit ${short(job.id)} queued.`, "ok");
    await refresh();
    return job;
  } catch (e) {
    if (e instanceof AuthError) throw e;
    say("upload-msg", `Could not start the fit: ${e.detail || e.message}`, "error");
  }
}

const upload = guard(async (ev) => {
  ev.preventDefault();
  const mesh = $("mesh-file").files[0];
  if (!mesh) return say("upload-msg", "Choose a mesh file first.", "error");
  const form = new FormData();
  form.append("mesh", mesh, mesh.name);
  const tex = $("texture-file").files[0];
  if (tex) form.append("texture", tex, tex.name);
  $("upload-btn").disabled = true;
  say("upload-msg", `Uploading and validating ${mesh.name}…`);
  try {
    const rec = await getJSON("/v1/meshes", { method: "POST", body: form });
    say("upload-msg", `Mesh ${rec.name}: ${rec.n_vertices} vertices, ${rec.n_faces} faces${rec.has_texture ? ", textured" : ""}.`, "ok");
    if ($("fit-after").checked) {
      if (!rec.has_texture) say("upload-msg", "Uploaded, but a UV fit needs a texture (choose one, or a mesh that embeds it).", "error");
      else await startFit(rec.id);
    } else {
      await refresh();
    }
  } catch (e) {
    if (e instanceof AuthError) throw e;
    say("upload-msg", `Upload refused: ${e.detail || e.message}`, "error");
  } finally {
    $("upload-btn").disabled = false;
  }
});

async function cancelJob(id) {
  try {
    await api(`/v1/jobs/${id}/cancel`, { method: "POST" });
  } catch (e) {
    if (e instanceof AuthError) throw e;
    say("jobs-msg", `Cancel failed: ${e.detail || e.message}`, "error");
  }
  await refresh();
}

async function retryJob(j) {
  const spectra = Object.fromEntries(SPECTRA_FIELDS.filter((k) => j.params?.spectra?.[k] != null).map((k) => [k, j.params.spectra[k]]));
  const body = { mesh_id: j.mesh_id, task: j.task, priority: j.priority, params: j.params?.params || {}, spectra };
  try {
    const job = await getJSON("/v1/jobs", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    say("jobs-msg", `Retried as ${short(job.id)}.`, "ok");
  } catch (e) {
    if (e instanceof AuthError) throw e;
    say("jobs-msg", `Retry refused: ${e.detail || e.message}`, "error");
  }
  await refresh();
}

async function download(path, name) {
  const url = await blobURL(path);
  const a = el("a", { href: url, download: name });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 30000);
}

// ------------------------------------------------------------------ viewer and pictures

async function openViewer(id) {
  const v = S.viewer;
  for (const url of Object.values(v.layers)) URL.revokeObjectURL(url);
  Object.assign(v, { id, layers: {}, textures: {}, bake: null });
  const mv = $("mv");
  mv.removeAttribute("data-layer");
  $("viewer-title").textContent = short(id);
  $("layer-kernel").checked = true;
  say("viewer-msg", `Baking ${short(id)} at ${BAKE_RESOLUTION}² (first time only)…`);
  $("viewer-card").scrollIntoView({ behavior: "smooth", block: "nearest" });
  let bake;
  try {
    bake = await getJSON(`/v1/kernelsets/${id}/bake?resolution=${BAKE_RESOLUTION}`);
  } catch (e) {
    if (e instanceof AuthError) throw e;
    return say("viewer-msg", `Bake failed: ${e.detail || e.message}`, "error");
  }
  if (v.id !== id) return; // another one was opened meanwhile
  v.bake = bake;
  const q = `?resolution=${BAKE_RESOLUTION}`;
  const glb = await blobURL(`/v1/kernelsets/${id}/glb${q}`);
  for (const layer of bake.layers) v.layers[layer] = await blobURL(`/v1/kernelsets/${id}/textures/${layer}${q}`);
  for (const layer of ["original", "error"]) {
    $(`layer-${layer}`).disabled = !bake.layers.includes(layer);
  }
  $("legend-max").textContent = bake.error_scale ? bake.error_scale.toFixed(2) : "";
  $("legend").hidden = true;
  await new Promise((resolve) => {
    mv.addEventListener("load", resolve, { once: true });
    mv.src = glb;
  });
  mv.setAttribute("data-layer", "kernel");
  const err = bake.error_rms != null ? `, texture RMS error ${bake.error_rms.toFixed(3)}` : "";
  say("viewer-msg", `${bake.layers.length} layer(s), ${bytes(bake.glb_bytes)} B GLB, ${bake.atlas} UVs, ` +
    `${(100 * bake.coverage).toFixed(0)}% texels covered${err}. Drag to orbit, scroll to zoom.`, "ok");
  showPictures(id, bake);
}

const setLayer = guard(async (layer) => {
  const v = S.viewer;
  const mv = $("mv");
  if (!v.bake || !v.layers[layer] || !mv.model) return;
  if (!v.textures[layer]) v.textures[layer] = await mv.createTexture(v.layers[layer]);
  for (const mat of mv.model.materials) mat.pbrMetallicRoughness.baseColorTexture.setTexture(v.textures[layer]);
  mv.setAttribute("data-layer", layer);
  $("legend").hidden = layer !== "error";
});

async function showPictures(id, bake) {
  $("pictures").hidden = false;
  $("pictures-title").textContent = short(id);
  for (const layer of ["kernel", "original", "error"]) {
    const img = $(`pic-${layer}`);
    img.closest("figure").hidden = !bake.layers.includes(layer);
    if (bake.layers.includes(layer)) img.src = S.viewer.layers[layer];
  }
  await showCurve(id);
  $("pic-render").closest("figure").hidden = true;
  say("pictures-msg", "Rendering a 512² preview on the service…");
  try {
    $("pic-render").src = await blobURL(`/v1/kernelsets/${id}/render?width=512&height=512&spp=16`);
    $("pic-render").closest("figure").hidden = false;
    say("pictures-msg", "");
  } catch (e) {
    if (e instanceof AuthError) throw e;
    $("pic-render").closest("figure").hidden = true;
    say("pictures-msg", `No render preview: ${e.detail || e.message}`, "error");
  }
}

// ------------------------------------------------------------------ start

window.addEventListener("DOMContentLoaded", () => {
  $("login-form").addEventListener("submit", (ev) => { ev.preventDefault(); signIn($("token").value.trim()); });
  $("signout").addEventListener("click", signOut);
  $("upload-form").addEventListener("submit", upload);
  for (const r of document.querySelectorAll("input[name=layer]")) r.addEventListener("change", () => setLayer(r.value));
  // a stored token, or none at all (a service without tokens answers every request as "local")
  signIn(S.token);
});
