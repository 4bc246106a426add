// The web page of `rllock serve`: pick or upload a shape, see N and the K that make sense, run a job and
// follow it live (server-sent events), then look at the assembly in 3D (rotate, zoom, hide pieces, a
// slider that plays the verified disassembly) and download its files. Bundled with three.js by esbuild.
import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

const $ = (id) => document.getElementById(id);
const FACES = [
  [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
];
const DIRECTION = { "+x": [1, 0, 0], "-x": [-1, 0, 0], "+y": [0, 1, 0], "-y": [0, -1, 0], "+z": [0, 0, 1], "-z": [0, 0, -1] };
const FINAL = new Set(["done", "failed", "cancelled"]);

const page = { shapeInfo: null, job: null, events: null, assembly: null, playing: null };

// ---- talking to the server -------------------------------------------------------------------------

async function api(path, options = {}) {
  const response = await fetch(path, options);
  const body = await response.json().catch(() => ({}));
  if (!response.ok) throw new Error(body.error || `${response.status} ${response.statusText}`);
  return body;
}

function showError(message) {
  $("error").textContent = message;
  $("error").hidden = !message;
  if (message) document.body.dataset.phase = "error";
}

// Mesh files, voxelized at the resolution the page asks for.
const MESH = /\.(stl|obj|ply|off|glb|gltf|3mf)$/i;

function shapeForm() {
  const form = new FormData();
  const file = $("shape-file").files[0];
  if (file) {
    form.append("file", file, file.name);
    if (MESH.test(file.name)) form.append("resolution", $("resolution").value);
  } else {
    form.append("shape", $("shape-name").value);
  }
  if ($("thicken").value) form.append("thicken", $("thicken").value);
  return form;
}

// ---- the 3D view -----------------------------------------------------------------------------------

const view = (() => {
  const host = $("view");
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  host.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xffffff);
  const camera = new THREE.PerspectiveCamera(40, 1, 0.1, 5000);
  camera.up.set(0, 0, 1);
  scene.add(new THREE.AmbientLight(0xffffff, 0.55));
  const sun = new THREE.DirectionalLight(0xffffff, 1.6);
  sun.position.set(2, -3, 4);
  scene.add(sun);
  const fill = new THREE.DirectionalLight(0xffffff, 0.5);
  fill.position.set(-3, 2, -1);
  scene.add(fill);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.enableDamping = true;
  let root = new THREE.Group();
  scene.add(root);

  function resize() {
    const w = host.clientWidth || 600, h = host.clientHeight || 400;
    renderer.setSize(w, h, false);
    renderer.domElement.style.width = "100%";
    renderer.domElement.style.height = "100%";
    camera.aspect = w / h;
    camera.updateProjectionMatrix();
  }
  window.addEventListener("resize", resize);
  resize();
  (function loop() {
    controls.update();
    renderer.render(scene, camera);
    requestAnimationFrame(loop);
  })();

  // One mesh per group of voxels: only the faces on its boundary, so thousands of voxels stay cheap.
  function boundaryMesh(voxels, color) {
    const filled = new Set(voxels.map((v) => v.join(",")));
    const positions = [], normals = [];
    for (const [x, y, z] of voxels) {
      for (const n of FACES) {
        if (filled.has(`${x + n[0]},${y + n[1]},${z + n[2]}`)) continue;
        const axis = n.findIndex((c) => c !== 0), sign = n[axis];
        const u = (axis + 1) % 3, w = (axis + 2) % 3;
        const corner = (du, dw) => {
          const p = [x, y, z];
          p[axis] += sign > 0 ? 1 : 0;
          p[u] += du;
          p[w] += dw;
          return p;
        };
        const quad = sign > 0 ? [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)] : [corner(0, 0), corner(0, 1), corner(1, 1), corner(1, 0)];
        for (const i of [0, 1, 2, 0, 2, 3]) {
          positions.push(...quad[i]);
          normals.push(...n);
        }
      }
    }
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.Float32BufferAttribute(positions, 3));
    geometry.setAttribute("normal", new THREE.Float32BufferAttribute(normals, 3));
    const mesh = new THREE.Mesh(geometry, new THREE.MeshLambertMaterial({ color, polygonOffset: true, polygonOffsetFactor: 1 }));
    const edges = new THREE.LineSegments(new THREE.EdgesGeometry(geometry, 30), new THREE.LineBasicMaterial({ color: 0x000000, transparent: true, opacity: 0.18 }));
    mesh.add(edges);
    return mesh;
  }

  function show(groups, dims) {
    scene.remove(root);
    root = new THREE.Group();
    const meshes = groups.map((g) => boundaryMesh(g.voxels, g.color));
    meshes.forEach((m) => root.add(m));
    root.position.set(-dims[0] / 2, -dims[1] / 2, -dims[2] / 2);
    scene.add(root);
    const radius = Math.hypot(...dims) / 2 + 1;
    camera.position.set(radius * 1.6, -radius * 2.2, radius * 1.5);
    controls.target.set(0, 0, 0);
    controls.update();
    return meshes;
  }

  return { show };
})();

function pieceColor(i) {
  const hue = (i * 0.618033988749895) % 1;
  const [s, v] = [[0.75, 0.95], [0.55, 0.8], [0.9, 0.7]][i % 3];
  const f = (n) => { const k = (n + hue * 6) % 6; return v - v * s * Math.max(0, Math.min(k, 4 - k, 1)); };
  return new THREE.Color(f(5), f(3), f(1));
}

function cellsOf(voxels, dims) {
  const [X, Y] = dims;
  return voxels.map((i) => [i % X, Math.floor(i / X) % Y, Math.floor(i / (X * Y))]);
}

// ---- shapes ----------------------------------------------------------------------------------------

// Previews overlap (a file chosen, then its resolution changed): only the latest one's answer is shown,
// whichever answer comes back last.
let previews = 0;

async function preview() {
  const mine = ++previews;
  showError("");
  document.body.dataset.phase = "preview";
  $("shape-info").textContent = "reading the shape…";
  try {
    const info = await api("/api/shape", { method: "POST", body: shapeForm() });
    if (mine !== previews) return;
    page.shapeInfo = info;
    const k = info.pieces;
    $("shape-info").textContent =
      `${info.name}: N = ${info.N} voxels, ${info.dimensions.join(" × ")}. K can be 2 to ${k.max}; ` +
      `pieces of 4 to 40 voxels: K = ${k.low} to ${k.high}. Left blank, the solver picks K: pieces of about ` +
      "20 voxels, or larger where those take it more than a few seconds." +
      (!$("thicken").value && info.thin_matters ?
        ` ${info.thin} voxels lie in thin parts (arms, legs, ears), where pieces have little room: ` +
        "growing them to 3 voxels, or larger pieces, helps." : "");
    $("pieces").max = k.max;
    $("pieces").value = "";
    view.show([{ voxels: cellsOf(info.voxels, info.dimensions), color: 0xb8bec6 }], info.dimensions);
    $("controls").hidden = true;
    document.body.dataset.phase = "ready";
    // When the page first showed a shape, for the browser test's first-view time.
    if (window.firstViewMs === undefined) window.firstViewMs = performance.now();
  } catch (e) {
    if (mine !== previews) return;
    $("shape-info").textContent = "";
    showError(e.message);
  }
}

async function loadShapes() {
  const shapes = await api("/api/shapes");
  const select = $("shape-name");
  for (const s of shapes) {
    const option = document.createElement("option");
    option.value = s.name;
    option.textContent = `${s.name} (N = ${s.N})`;
    select.appendChild(option);
  }
  select.value = "cube4";
}

// ---- jobs ------------------------------------------------------------------------------------------

// K of a job: asked for, or chosen by the server (its progress, then its result) when left blank.
function pieceCount(job) {
  return job.spec.pieces ?? job.progress?.pieces ?? job.result?.pieces ?? null;
}

function describe(job) {
  const p = job.progress;
  const spec = job.spec;
  const k = pieceCount(job);
  const what = `${spec.method} ${spec.shape} K=${k ?? "auto"}`;
  if (job.state === "queued") return `${what}: waiting in the queue (place ${job.queue_position ?? "?"})`;
  if (job.state === "running") {
    if (!p) return `${what}: starting…`;
    if (p.choosing !== undefined) {
      return `${what}: choosing K, pieces of about 20 voxels or larger (up to ${p.choosing} s)…`;
    }
    if (p.probe !== undefined) {
      return `${what}: no assembly within ${spec.time_limit} s; looking for a task near it that works (up to ${p.probe} s)…`;
    }
    return `${what}: best ${p.placed} of ${k - 1} pieces placed, ${p.elapsed} s` +
      (p.nodes !== undefined ? `, ${p.nodes} nodes` : `, ${p.episodes} episodes`);
  }
  if (job.state === "done") return `${what}: a valid assembly in ${job.result.seconds.toFixed(1)} s, verified.`;
  if (job.state === "cancelled") return `${what}: cancelled.`;
  return `${what}: failed.`;
}

function follow(job) {
  if (page.events) page.events.close();
  page.job = job;
  $("cancel").disabled = false;
  $("start").disabled = true;
  document.body.dataset.phase = "running";
  const events = new EventSource(`/api/jobs/${job.id}/events`);
  page.events = events;
  events.onmessage = (message) => {
    const now = JSON.parse(message.data);
    page.job = now;
    $("state").textContent = describe(now);
    const p = now.progress;
    const k = pieceCount(now);
    $("progress").value = now.state === "done" ? 1 : p && k ? Math.max(p.placed, 0) / Math.max(k - 1, 1) : 0;
    if (!FINAL.has(now.state)) return;
    events.close();
    $("cancel").disabled = true;
    $("start").disabled = false;
    if (now.state === "done") showAssembly(now);
    else if (now.state === "failed") {
      showError(now.error);
      if (now.result && now.result.offer) showOffer(now.result.offer);
    }
    else document.body.dataset.phase = "ready";
  };
  events.onerror = () => {
    if (page.job && !FINAL.has(page.job.state)) $("state").textContent = "lost touch with the server; retrying…";
  };
}

// A failed solve's nearest task that works (found by the server's probe with the same seed): one click
// runs it.
function showOffer(offer) {
  const grown = offer.thicken ? `, thin parts grown to ${offer.thicken}` : "";
  $("offer").textContent = `Run K=${offer.pieces}${grown} (pieces of ${offer.piece_size}, the last ` +
    `${offer.last_size}): found in ${offer.seconds} s`;
  $("offer").onclick = async () => {
    const thicken = offer.thicken ? String(offer.thicken) : "";
    if ($("thicken").value !== thicken) {
      $("thicken").value = thicken;
      await preview(); // the grown shape on view; it leaves K blank
    }
    $("pieces").value = offer.pieces;
    // Time enough for the same search on a busier server: it found it in offer.seconds.
    const enough = Math.ceil(3 * offer.seconds) + 5;
    if (Number($("time-limit").value) < enough) $("time-limit").value = enough;
    $("job-form").requestSubmit();
  };
  $("offer-row").hidden = false;
}

async function start(event) {
  event.preventDefault();
  showError("");
  $("offer-row").hidden = true;
  const form = shapeForm();
  if ($("pieces").value) form.append("pieces", $("pieces").value);
  form.append("removal", $("removal").value);
  form.append("method", $("method").value);
  form.append("time_limit", $("time-limit").value);
  try {
    const job = await api("/api/jobs", { method: "POST", body: form });
    $("downloads").hidden = true;
    $("state").textContent = describe(job);
    follow(job);
  } catch (e) {
    showError(e.message);
  }
}

async function cancel() {
  if (!page.job) return;
  try {
    await api(`/api/jobs/${page.job.id}/cancel`, { method: "POST" });
  } catch (e) {
    showError(e.message);
  }
}

// ---- the assembly ----------------------------------------------------------------------------------

async function showAssembly(job) {
  const doc = await (await fetch(job.files["assembly.json"])).json();
  const dims = doc.dimensions, k = doc.K;
  const voxels = Array.from({ length: k }, () => []);
  doc.labels.forEach((label, i) => { if (label > 0) voxels[label - 1].push(i); });
  const meshes = view.show(voxels.map((v, i) => ({ voxels: cellsOf(v, dims), color: pieceColor(i) })), dims);
  // Each piece's way out: its verified moves, then on until it is clear of the shape.
  const paths = Array.from({ length: k }, () => [[0, 0, 0]]);
  for (const step of doc.disassembly) {
    const path = paths[step.piece - 1];
    let at = [0, 0, 0], last = [0, 0, 1];
    for (const move of step.moves) {
      last = DIRECTION[move.direction];
      at = at.map((c, a) => c + last[a] * move.steps);
      path.push(at);
    }
    path.push(at.map((c, a) => c + last[a] * Math.ceil(Math.max(...dims) / 2)));
  }
  page.assembly = { k, meshes, paths, hidden: new Set() };
  buildPieceList(k);
  const slider = $("slider");
  slider.max = String(Math.max(k - 1, 1));
  slider.value = "0";
  place(0);
  $("controls").hidden = false;
  const base = `/api/jobs/${job.id}`;
  $("download-puz").href = `${base}/files/assembly.puz`;
  $("download-json").href = `${base}/files/assembly.json`;
  $("download-png").href = `${base}/files/assembly.png`;
  updateZipLink();
  $("downloads").hidden = false;
  document.body.dataset.phase = "assembly";
}

function updateZipLink() {
  if (!page.job) return;
  const query = new URLSearchParams({ gap: $("gap").value, voxel_size: $("voxel-size").value });
  $("download-zip").href = `/api/jobs/${page.job.id}/pieces.zip?${query}`;
}

function along(path, t) {
  // The point a fraction t of the way along a polyline.
  const lengths = path.slice(1).map((p, i) => Math.hypot(...p.map((c, a) => c - path[i][a])));
  let left = t * lengths.reduce((a, b) => a + b, 0);
  for (let i = 0; i < lengths.length; i++) {
    if (left <= lengths[i] || i === lengths.length - 1) {
      const f = lengths[i] ? Math.min(left / lengths[i], 1) : 0;
      return path[i].map((c, a) => c + (path[i + 1][a] - c) * f);
    }
    left -= lengths[i];
  }
  return path[0];
}

// Slider value s: pieces 1..floor(s) have left; piece floor(s)+1 is on its way out.
function place(s) {
  const { k, meshes, paths, hidden } = page.assembly;
  for (let i = 0; i < k; i++) {
    const t = Math.min(Math.max(s - i, 0), 1);
    const gone = i < k - 1 && t >= 1;
    meshes[i].visible = !gone && !hidden.has(i);
    meshes[i].position.set(...(paths[i].length > 1 ? along(paths[i], t) : [0, 0, 0]));
  }
  const moving = Math.min(Math.floor(s), k - 2);
  $("step-caption").textContent = s <= 0 ? `assembled: ${k} pieces` :
    s >= k - 1 ? `piece ${k} stays` : `piece ${moving + 1}${moving === 0 ? " (the key)" : ""} comes out`;
}

function buildPieceList(k) {
  const list = $("piece-list");
  list.textContent = "";
  for (let i = 0; i < k; i++) {
    const label = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox";
    box.checked = true;
    box.dataset.piece = String(i + 1);
    box.addEventListener("change", () => {
      if (box.checked) page.assembly.hidden.delete(i); else page.assembly.hidden.add(i);
      place(Number($("slider").value));
    });
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = `#${pieceColor(i).getHexString()}`;
    label.append(box, swatch, String(i + 1));
    list.appendChild(label);
  }
}

function play() {
  if (page.playing) { cancelAnimationFrame(page.playing); page.playing = null; return; }
  const slider = $("slider"), end = Number(slider.max);
  let s = Number(slider.value) >= end ? 0 : Number(slider.value), last = performance.now();
  const tick = (now) => {
    s = Math.min(s + (now - last) / 700, end);
    last = now;
    slider.value = String(s);
    place(s);
    page.playing = s < end ? requestAnimationFrame(tick) : null;
  };
  page.playing = requestAnimationFrame(tick);
}

// ---- wiring ----------------------------------------------------------------------------------------

$("shape-name").addEventListener("change", () => { $("shape-file").value = ""; $("resolution-row").hidden = true; preview(); });
$("shape-file").addEventListener("change", () => {
  const file = $("shape-file").files[0];
  $("resolution-row").hidden = !(file && MESH.test(file.name));
  preview();
});
$("resolution").addEventListener("change", preview);
$("thicken").addEventListener("change", preview);
$("job-form").addEventListener("submit", start);
$("cancel").addEventListener("click", cancel);
$("slider").addEventListener("input", () => place(Number($("slider").value)));
$("play").addEventListener("click", play);
$("gap").addEventListener("input", updateZipLink);
$("voxel-size").addEventListener("input", updateZipLink);

loadShapes().then(preview).catch((e) => showError(e.message));
