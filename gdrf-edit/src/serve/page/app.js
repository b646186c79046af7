// gdrf-edit serve's page: every image comes from /api/render with this page's client id, so
// that the server drops this page's stale requests. While the view moves it asks for a
// small image first, and for the full one once the view has been still for a moment.
"use strict";

const $ = (id) => document.getElementById(id);
const client = (crypto.randomUUID ? crypto.randomUUID() : String(Math.random()).slice(2));
const state = { yaw: 0, pitch: 60, fov: 50, info: null, turning: null, settle: null, inflight: false, again: false };
const STILL_MS = 150;

function status(text, isError) {
  const s = $("status");
  s.textContent = text;
  s.className = isError ? "error" : "";
}

function showAngles() {
  $("yaw-out").textContent = (((state.yaw % 360) + 360) % 360).toFixed(0);
  $("pitch-out").textContent = state.pitch.toFixed(0);
  $("fov-out").textContent = state.fov.toFixed(0);
}

// The query of the current view: sources, blends, camera and quality; `res` overrides the
// resolution (the small image while moving).
function viewQuery(res) {
  const q = new URLSearchParams();
  for (const k of ["shape", "appearance"]) {
    q.set(k, $(k).value.trim());
    const b = $(k + "_b").value.trim();
    if (b) { q.set(k + "_b", b); q.set(k + "_t", $(k + "_t").value); }
  }
  q.set("yaw", state.yaw.toFixed(2));
  q.set("pitch", state.pitch.toFixed(2));
  q.set("fov", state.fov.toFixed(2));
  q.set("psi", $("psi").value);
  q.set("res", String(res || $("res").value));
  q.set("samples", $("samples").value);
  return q;
}

async function errorText(r) {
  try { return (await r.json()).error; } catch (e) { return r.status + " " + r.statusText; }
}

// Renders the view now at `res` (the full resolution when absent). One request at a time:
// a render asked for meanwhile runs when it ends, with the view as it is then.
async function render(res) {
  if (state.inflight) { state.again = res || true; return; }
  state.inflight = true;
  try {
    const q = viewQuery(res);
    q.set("client", client);
    const r = await fetch("/api/render?" + q);
    if (r.status === 409) return; // superseded by a newer request of this page
    if (!r.ok) { status(await errorText(r), true); return; }
    const blob = await r.blob();
    const old = $("view").src;
    $("view").src = URL.createObjectURL(blob);
    if (old.startsWith("blob:")) URL.revokeObjectURL(old);
    $("view").dataset.yaw = q.get("yaw");
    $("view").dataset.res = q.get("res");
    status(q.get("res") + "² in " + r.headers.get("X-Render-Ms") + " ms");
  } catch (e) {
    status("the server did not answer: " + e, true);
  } finally {
    state.inflight = false;
    if (state.again) {
      const again = state.again;
      state.again = false;
      render(again === true ? undefined : again);
    }
  }
}

// The view moved: a small image now, the full one when it has been still for a moment.
function moved() {
  showAngles();
  const full = Number($("res").value);
  render(Math.min(full, 32));
  clearTimeout(state.settle);
  state.settle = setTimeout(() => render(), STILL_MS);
}

function setupDrag() {
  const img = $("view");
  let last = null;
  img.addEventListener("pointerdown", (e) => {
    last = [e.clientX, e.clientY];
    img.setPointerCapture(e.pointerId);
    img.classList.add("dragging");
  });
  img.addEventListener("pointermove", (e) => {
    if (!last) return;
    state.yaw -= (e.clientX - last[0]) * 0.5;
    state.pitch = Math.min(179, Math.max(1, state.pitch - (e.clientY - last[1]) * 0.3));
    last = [e.clientX, e.clientY];
    moved();
  });
  const end = () => { last = null; img.classList.remove("dragging"); };
  img.addEventListener("pointerup", end);
  img.addEventListener("pointercancel", end);
  img.addEventListener("wheel", (e) => {
    e.preventDefault();
    state.fov = Math.min(120, Math.max(5, state.fov * Math.exp(e.deltaY * 0.001)));
    moved();
  }, { passive: false });
}

function setupTurntable() {
  $("turntable").addEventListener("click", () => {
    if (state.turning) {
      clearInterval(state.turning);
      state.turning = null;
      $("turntable").textContent = "turntable";
      render();
      return;
    }
    $("turntable").textContent = "stop";
    state.turning = setInterval(() => { state.yaw += 6; moved(); }, 100);
  });
}

function addSources(names) {
  const list = $("sources");
  const have = new Set([...list.options].map((o) => o.value));
  for (const n of names) {
    if (have.has(n)) continue;
    const o = document.createElement("option");
    o.value = n;
    list.appendChild(o);
  }
}

// Uploads a photo, follows its inversion and offers its features as a source when done.
async function invertPhoto(file) {
  const p = $("photo-progress");
  const say = (t, bad) => { $("photo-status").textContent = t; $("photo-status").className = bad ? "error" : ""; };
  say("uploading " + file.name);
  const r = await fetch("/api/photo", { method: "POST", body: file });
  if (!r.ok) { say(await errorText(r), true); return; }
  const { id, source } = await r.json();
  p.hidden = false;
  p.value = 0;
  for (;;) {
    await new Promise((ok) => setTimeout(ok, 300));
    const s = await (await fetch("/api/photo/" + id)).json();
    if (s.state === "running") { p.value = s.step / s.steps; say("inverting " + file.name + ": step " + s.step + " of " + s.steps); }
    else if (s.state === "queued") say(file.name + " waits for another inversion");
    else if (s.state === "done") { p.hidden = true; addSources([source]); say(file.name + " is " + source + ": choose it as a shape or an appearance"); return source; }
    else { p.hidden = true; say(file.name + ": " + (s.error || "failed"), true); return; }
  }
}

function setupPhotos() {
  $("photo").addEventListener("change", (e) => { if (e.target.files[0]) invertPhoto(e.target.files[0]); });
  document.addEventListener("dragover", (e) => { e.preventDefault(); document.body.classList.add("dropping"); });
  document.addEventListener("dragleave", (e) => { if (!e.relatedTarget) document.body.classList.remove("dropping"); });
  document.addEventListener("drop", (e) => {
    e.preventDefault();
    document.body.classList.remove("dropping");
    const f = e.dataTransfer.files[0];
    if (f) invertPhoto(f);
  });
}

// Downloads one export of the current view through a link, with its progress shown.
async function download(kind) {
  const q = viewQuery();
  const paths = {
    png: ["/api/render", "gdrf.png"],
    orbit: ["/api/export/orbit", "orbit.gif"],
    mesh: ["/api/export/mesh", "mesh.ply"],
    features: ["/api/export/features", "features.safetensors"],
    matrix: ["/api/export/matrix", "swap-matrix.png"],
  };
  if (kind === "features") q.set("source", $("shape").value.trim());
  if (kind === "matrix") {
    const picked = ["shape", "appearance", "shape_b", "appearance_b"].map((k) => $(k).value.trim()).filter((v) => v);
    q.set("sources", [...new Set(picked)].join(","));
  }
  const [path, name] = paths[kind];
  $("export-progress").hidden = false;
  $("export-status").textContent = "making " + name;
  try {
    const r = await fetch(path + "?" + q);
    if (!r.ok) { $("export-status").textContent = await errorText(r); return; }
    const a = document.createElement("a");
    a.href = URL.createObjectURL(await r.blob());
    a.download = name;
    document.body.appendChild(a);
    a.click();
    a.remove();
    $("export-status").textContent = name + " (" + r.headers.get("X-Render-Ms") + " ms)";
  } finally {
    $("export-progress").hidden = true;
  }
}

async function start() {
  const r = await fetch("/api/info");
  const info = await r.json();
  state.info = info;
  state.pitch = info.pitch_deg;
  state.fov = info.fov_deg;
  $("model").textContent = "generator " + info.generator + ", learned at " + info.learned_resolution + "²";
  for (const res of [32, 64, 128, 256, 512]) {
    if (res > info.max_resolution) break;
    const o = document.createElement("option");
    o.value = o.textContent = res;
    $("res").appendChild(o);
  }
  $("res").value = String(info.default_resolution);
  $("samples").value = info.default_samples;
  $("samples").max = info.max_samples;
  addSources(["seed:0", "seed:1", "seed:2", "seed:3"]);
  addSources(info.features.map((n) => "features:" + n));
  addSources(info.photos.map((id) => "photo:" + id));
  for (const id of ["shape", "appearance", "shape_b", "appearance_b", "res", "samples"]) $(id).addEventListener("change", () => render());
  for (const id of ["shape_t", "appearance_t", "psi"]) {
    $(id).addEventListener("input", () => { $("psi-out").textContent = $("psi").value; moved(); });
  }
  for (const b of document.querySelectorAll("[data-export]")) b.addEventListener("click", () => download(b.dataset.export));
  setupDrag();
  setupTurntable();
  setupPhotos();
  showAngles();
  render();
}

start().catch((e) => status("could not start: " + e, true));
