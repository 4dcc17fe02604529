// visionpos operator console: one WebSocket, a three.js arena, a 2-D canvas per camera, health tables.
// Messages (console/server.py): scene (once per connection), state (update_rate_hz), health (1 Hz), replay, error.
// Truth on screen: no message for STALE_MS, or a closed socket, greys the page with "no data since HH:MM:SS";
// a scene with another scene_id (a restart into another arena) rebuilds the 3D view and the camera views.
import * as THREE from "three";
import { OrbitControls } from "./vendor/OrbitControls.js";
import { calibMessage, calibReplay } from "./calib.js";
import { initRecord, recordMessage } from "./record.js";
import { initMonitor, monitorMessage } from "./monitor.js";
import { drawStationLayer, initStationTools, onStationMessage, proposeMask, resetStationTools, stationTools }
  from "./stills.js";

const BODY_COLORS = [0x44ccff, 0xff66cc, 0x88ee66, 0xffdd44, 0xaa88ff, 0xff8844];
const LEFT_COLOR = "#ffaa44";
const TRAIL_POINTS = 90;       // a short trail: 3 s at 30 updates/s
const FRUSTUM_DEPTH_M = 0.35;
const RAY_LENGTH_M = 8;
const CAM_VIEW_WIDTH_PX = 300;
const STALE_MS = 2000;         // no update for this long: the page is not live
const RATE_WINDOW_MS = 2000;   // the page's own update rate, counted over this window

// what the browser tests read (tests/console/test_browser.py)
const stats = { scenes: 0, states: 0, health: 0, errors: [], blobs: {}, frames3d: 0, rebuilds: 0, stale: true,
  staleText: "", updatesPerS: null };
window.visionposConsole = stats;

const params = new URLSearchParams(location.search);
const token = params.get("token");
let ws = null;
let scene3 = null;
let sceneMsg = null;
const camViews = new Map();

function hex(c) { return "#" + c.toString(16).padStart(6, "0"); }
function fmt(x, d = 1) { return x === null || x === undefined ? "-" : Number(x).toFixed(d); }
function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

// ------------------------------------------------------------------ 3D view

class Arena3D {
  constructor(canvas, msg) {
    this.canvas = canvas;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x15181c);
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.05, 200);
    this.camera.up.set(0, 0, 1);  // world z is up
    this.controls = new OrbitControls(this.camera, canvas);
    this.load(msg);
    this.resize();
    new ResizeObserver(() => this.resize()).observe(canvas);
    const loop = () => { this.controls.update(); this.renderer.render(this.scene, this.camera); stats.frames3d++;
      requestAnimationFrame(loop); };
    loop();
  }

  // the arena's cameras and bodies, from nothing: a rebuild (another arena) leaves no frustum, body or trail behind
  load(msg) {
    for (const o of [...this.scene.children]) {
      this.scene.remove(o);
      o.traverse(x => { x.geometry?.dispose(); x.material?.map?.dispose(); x.material?.dispose(); });
    }
    this.cameraPoses = msg.cameras;
    this.frusta = msg.cameras.length;
    this.bodies = msg.bodies.map((b, i) => this.makeBody(b, i));
    this.markers = new THREE.Points(new THREE.BufferGeometry(),
      new THREE.PointsMaterial({ color: 0xffaa44, size: 6, sizeAttenuation: false }));
    this.scene.add(this.markers);
    this.rays = new THREE.LineSegments(new THREE.BufferGeometry(),
      new THREE.LineBasicMaterial({ color: 0xffee88, transparent: true, opacity: 0.6 }));
    this.scene.add(this.rays);
    this.rayCamera = null;
    this.addWorld(msg.cameras);
    this.volume = msg.volume ? this.addVolume(msg.volume) : null;
  }

  // the planner's flight volume (plan.volume): a cyan box
  addVolume(v) {
    const size = [0, 1, 2].map(i => v.max_m[i] - v.min_m[i]);
    const box = new THREE.LineSegments(new THREE.EdgesGeometry(new THREE.BoxGeometry(...size)),
      new THREE.LineBasicMaterial({ color: 0x44ccdd }));
    box.position.set(...[0, 1, 2].map(i => (v.max_m[i] + v.min_m[i]) / 2));
    this.scene.add(box);
    return { center: box.position.toArray(), size };
  }

  addWorld(cams) {
    // the floor grid spans the cameras' footprint, at least 4 m
    let extent = 2;
    for (const c of cams) extent = Math.max(extent, Math.abs(c.position[0]) + 0.5, Math.abs(c.position[1]) + 0.5);
    const size = 2 * Math.ceil(extent);
    const grid = new THREE.GridHelper(size, size * 2, 0x556070, 0x2c3540);
    grid.rotation.x = Math.PI / 2;  // GridHelper lies in x-z; the floor is x-y
    this.scene.add(grid);
    this.scene.add(new THREE.AxesHelper(0.5));
    for (const c of cams) this.scene.add(this.frustum(c));
    const h = Math.max(2, ...cams.map(c => c.position[2]));
    this.camera.position.set(extent * 1.0, -extent * 1.25, h * 1.1 + 0.5);
    this.controls.target.set(0, 0, 0.5);
  }

  toWorld(c, p) {
    const R = c.R_c2w;
    return new THREE.Vector3(
      R[0][0] * p[0] + R[0][1] * p[1] + R[0][2] * p[2] + c.position[0],
      R[1][0] * p[0] + R[1][1] * p[1] + R[1][2] * p[2] + c.position[1],
      R[2][0] * p[0] + R[2][1] * p[1] + R[2][2] * p[2] + c.position[2]);
  }

  frustum(c) {
    const d = FRUSTUM_DEPTH_M;
    const corners = [[0, 0], [c.width, 0], [c.width, c.height], [0, c.height]].map(([u, v]) =>
      this.toWorld(c, [(u - c.cx) / c.fx * d, (v - c.cy) / c.fy * d, d]));
    const o = new THREE.Vector3(...c.position);
    const pts = [];
    for (let i = 0; i < 4; i++) pts.push(o, corners[i], corners[i], corners[(i + 1) % 4]);
    const g = new THREE.BufferGeometry().setFromPoints(pts);
    const group = new THREE.Group();
    group.add(new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: 0xc0c8d0 })));
    const top = this.toWorld(c, [0, -c.cy / c.fy * d * 1.25, d]);  // a tick on the image's top edge
    group.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints([corners[0].clone().lerp(corners[1], 0.5), top]),
      new THREE.LineBasicMaterial({ color: 0xc0c8d0 })));
    return group;
  }

  makeBody(b, i) {
    const color = BODY_COLORS[i % BODY_COLORS.length];
    const group = new THREE.Group();
    group.add(new THREE.AxesHelper(0.15));
    const geom = new THREE.SphereGeometry(0.012, 10, 8);
    const mat = new THREE.MeshBasicMaterial({ color });
    for (const m of b.markers) { const s = new THREE.Mesh(geom, mat); s.position.set(...m); group.add(s); }
    group.visible = false;
    this.scene.add(group);
    const trailGeom = new THREE.BufferGeometry();
    trailGeom.setAttribute("position", new THREE.BufferAttribute(new Float32Array(TRAIL_POINTS * 3), 3));
    trailGeom.setDrawRange(0, 0);
    const trail = new THREE.Line(trailGeom, new THREE.LineBasicMaterial({ color }));
    trail.frustumCulled = false;
    this.scene.add(trail);
    const label = this.label(b.name, color);
    label.visible = false;
    this.scene.add(label);
    group.userData.body = i;
    label.userData.body = i;
    return { group, trail, label, n: 0, name: b.name };
  }

  // the body's name above it, always facing the viewer, the same size on screen at any distance
  label(text, color) {
    const c = el("canvas");
    c.width = 256; c.height = 64;
    const g = c.getContext("2d");
    g.font = "bold 40px system-ui, sans-serif";
    g.fillStyle = hex(color);
    g.textAlign = "center"; g.textBaseline = "middle";
    g.fillText(text, 128, 32);
    const tex = new THREE.CanvasTexture(c);
    const sprite = new THREE.Sprite(new THREE.SpriteMaterial({ map: tex, depthTest: false, sizeAttenuation: false }));
    sprite.scale.set(0.16, 0.04, 1);
    sprite.center.set(0.5, -0.4);
    return sprite;
  }

  // the body under a click (client coordinates), or -1
  pick(x, y) {
    const r = this.canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2((x - r.left) / r.width * 2 - 1, -(y - r.top) / r.height * 2 + 1);
    const ray = new THREE.Raycaster();
    ray.params.Line.threshold = 0.02;
    ray.setFromCamera(ndc, this.camera);
    const targets = this.bodies.filter(b => b.group.visible).flatMap(b => [b.group, b.label]);
    for (const hit of ray.intersectObjects(targets, true)) {
      for (let o = hit.object; o; o = o.parent) if (o.userData.body !== undefined) return o.userData.body;
    }
    return -1;
  }

  // where a body is on the page (client coordinates), for the browser tests' clicks
  screenOf(i) {
    const b = this.bodies[i];
    if (!b || !b.group.visible) return null;
    const p = b.group.position.clone().project(this.camera);
    const r = this.canvas.getBoundingClientRect();
    return [r.left + (p.x + 1) / 2 * r.width, r.top + (1 - p.y) / 2 * r.height];
  }

  // view presets: the whole arena from above or from the front, or through one camera (its pose and field of view)
  preset(name) {
    const cams = this.cameraPoses;
    const extent = Math.max(2, ...cams.map(c => Math.max(Math.abs(c.position[0]), Math.abs(c.position[1])) + 0.5));
    this.camera.fov = 50;
    if (name === "top") {
      this.camera.position.set(0, -0.001, extent * 2.6);  // a hair off the vertical: "up" stays defined
      this.controls.target.set(0, 0, 0);
    } else if (name === "front") {
      this.camera.position.set(0, -extent * 2.4, 1.2);
      this.controls.target.set(0, 0, 0.8);
    } else if (name.startsWith("camera ")) {
      const c = cams.find(k => String(k.id) === name.slice(7));
      if (!c) return;
      const ahead = this.toWorld(c, [0, 0, 1]);
      this.camera.position.set(...c.position);
      this.controls.target.copy(ahead);
      this.camera.fov = 2 * Math.atan(c.height / 2 / c.fy) * 180 / Math.PI;
    }
    this.camera.updateProjectionMatrix();
    this.controls.update();
    stats.view3d = { preset: name, position: this.camera.position.toArray(), target: this.controls.target.toArray(),
      fov: this.camera.fov };
  }

  update(msg) {
    msg.bodies.forEach((b, i) => {
      const v = this.bodies[i];
      if (!v) return;
      v.group.visible = v.label.visible = b.tracked;
      if (!b.tracked) return;
      v.group.position.set(...b.p);
      v.label.position.set(b.p[0], b.p[1], b.p[2] + 0.12);
      v.group.quaternion.set(...b.q);  // x, y, z, w: the same order as visionpos
      const arr = v.trail.geometry.attributes.position.array;
      if (v.n === TRAIL_POINTS) { arr.copyWithin(0, 3); v.n--; }
      arr.set(b.p, v.n * 3);
      v.n++;
      v.trail.geometry.setDrawRange(0, v.n);
      v.trail.geometry.attributes.position.needsUpdate = true;
    });
    const flat = msg.markers.flat().map(x => x ?? 0);
    this.markers.geometry.setAttribute("position", new THREE.Float32BufferAttribute(flat, 3));
    if (!msg.cameras) return;  // the rays move with the camera views
    const rays = [];
    const cam = this.cameraPoses.find(c => String(c.id) === this.rayCamera);
    const view = cam && msg.cameras.find(c => c.id === cam.id);
    if (view && view.rays) {
      const o = new THREE.Vector3(...cam.position);
      for (const [x5, y5] of view.rays) {
        const xn = x5 * 1e-5, yn = y5 * 1e-5;  // undistorted image coordinates, sent x 1e5
        const n = Math.hypot(xn, yn, 1);
        const end = this.toWorld(cam, [xn / n * RAY_LENGTH_M, yn / n * RAY_LENGTH_M, RAY_LENGTH_M / n]);
        rays.push(o.x, o.y, o.z, end.x, end.y, end.z);
      }
    }
    this.rays.geometry.setAttribute("position", new THREE.Float32BufferAttribute(rays, 3));
  }

  resize() {
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
  }
}

// ------------------------------------------------------------------ camera views

class CameraView {
  constructor(c, replay) {
    this.c = c;
    this.scale = CAM_VIEW_WIDTH_PX / c.width;
    const box = el("div", undefined, "cam");
    this.title = el("div", `camera ${c.id} (${c.name})`, "camtitle");
    this.canvas = el("canvas");
    this.canvas.id = `cam-${c.id}`;
    this.canvas.width = Math.round(c.width * this.scale);
    this.canvas.height = Math.round(c.height * this.scale);
    box.append(this.title, this.canvas);
    if (!replay) stationTools(this, box);  // still image and mask (stills.js): a replay has no station to ask
    document.getElementById("camgrid").append(box);
    this.mask = null;
    if (c.mask && c.mask.mask_png) {
      this.mask = new Image();
      this.mask.src = c.mask.mask_png;
    }
    this.draw({ blobs: [], pred: [], age_ms: null });
  }

  draw(v) {
    const g = this.canvas.getContext("2d"), s = this.scale;
    g.fillStyle = "#0d0f12";
    g.fillRect(0, 0, this.canvas.width, this.canvas.height);
    g.strokeStyle = "#2c323a";
    g.strokeRect(0.5, 0.5, this.canvas.width - 1, this.canvas.height - 1);
    drawStationLayer(this, g);
    this.drawMask(g, s);
    let matched = 0, left = 0;
    this.seen = new Set(v.blobs.filter(b => b[2] >= 0).map(b => b[2]));  // the bodies this camera sees
    const s10 = s / 10;  // pixels arrive in tenths
    for (const [u, vv, body] of v.blobs) {
      g.fillStyle = body >= 0 ? hex(BODY_COLORS[body % BODY_COLORS.length]) : LEFT_COLOR;
      g.beginPath();
      g.arc(u * s10, vv * s10, 4, 0, 2 * Math.PI);
      g.fill();
      body >= 0 ? matched++ : left++;
    }
    g.lineWidth = 1.5;
    for (const [u10, v10, body] of v.pred) {
      const u = u10 * s10, vv = v10 * s10;
      g.strokeStyle = hex(BODY_COLORS[body % BODY_COLORS.length]);
      g.beginPath();
      g.moveTo(u - 7, vv); g.lineTo(u + 7, vv);
      g.moveTo(u, vv - 7); g.lineTo(u, vv + 7);
      g.stroke();
    }
    this.title.textContent = `camera ${this.c.id} (${this.c.name}): ${matched} matched, ${left} left over` +
      (v.age_ms === null ? ", no frame yet" : `, frame ${fmt(v.age_ms, 0)} ms old`);
    this.title.title = this.title.textContent;  // the box keeps its size: a long title ends in an ellipsis
    stats.blobs[this.c.id] = v.blobs.length;
  }

  // the station's search area (console.stations): excluded pixels dimmed, ROIs green, ignore rectangles red
  drawMask(g, s) {
    const m = this.c.mask;
    if (!m) return;
    if (this.mask && this.mask.complete) {
      if (!this.dim) this.dim = this.excluded();
      if (this.dim) g.drawImage(this.dim, 0, 0, this.canvas.width, this.canvas.height);
    }
    g.lineWidth = 1;
    for (const [key, color] of [["rois", "#5c5"], ["ignore", "#e55"]]) {
      g.strokeStyle = color;
      for (const [x0, y0, x1, y1] of m[key]) g.strokeRect(x0 * s + 0.5, y0 * s + 0.5, (x1 - x0) * s, (y1 - y0) * s);
    }
  }

  excluded() {
    const w = this.mask.naturalWidth, h = this.mask.naturalHeight;
    if (!w || !h) return null;
    const c = el("canvas");
    c.width = w; c.height = h;
    const g = c.getContext("2d");
    g.drawImage(this.mask, 0, 0);
    const img = g.getImageData(0, 0, w, h);
    for (let i = 0; i < img.data.length; i += 4) {
      const searched = img.data[i] > 127;
      img.data[i] = 120; img.data[i + 1] = 40; img.data[i + 2] = 40; img.data[i + 3] = searched ? 0 : 90;
    }
    g.putImageData(img, 0, 0);
    return c;
  }
}

// ------------------------------------------------------------------ health

// rows: [level, cells]; a row's level ("ok", "warn": a configured rate not met, "bad": stops a flight or shows
// nothing true) colours it; cells: [text, class, title]
function fillTable(id, rows) {
  const body = document.querySelector(`#${id} tbody`);
  body.replaceChildren(...rows.map(([level, cells]) => {
    const tr = el("tr", undefined, `row-${level || "ok"}`);
    for (const [text, cls, title] of cells) {
      const td = el("td", text, cls);
      if (title) td.title = title;
      tr.append(td);
    }
    return tr;
  }));
}

function alerts(row) { const t = (row.alerts || []).join("; "); return [t, "alerts", t]; }
function rate(x, configured) { return `${fmt(x, 0)} (${fmt(configured, 0)})`; }
function ago(s) { return s === null || s === undefined ? "-" : s < 1 ? `${fmt(1000 * s, 0)} ms` : `${fmt(s, 1)} s`; }

// the warnings, what stops a flight first; a camera's static blobs are one line with a "mask these" action
function showWarnings(h) {
  const items = h.warnings.map(w => el("li", w));
  for (const r of h.reflections || []) {
    const i = h.warnings.findIndex(w => w.startsWith(`camera ${r.camera} (`) && w.includes("stayed put"));
    const view = camViews.get(r.camera);
    if (i < 0 || !view || !view.drawBtn) continue;
    const b = el("button", "mask these", "maskthese");
    b.title = "draw these rectangles on the camera view; check them, then \"save mask\" sends them to the station";
    b.onclick = () => proposeMask(view, r.ignore);
    b.dataset.camera = String(r.camera);
    b.dataset.ignore = JSON.stringify(r.ignore);
    items[i].append(" ", b);
  }
  document.getElementById("warnings").replaceChildren(...items);
}

let lastHealth = null;
function showHealth(h) {
  lastHealth = h;
  stats.health++;
  stats.healthTimes = (stats.healthTimes || []).concat([Date.now()]).slice(-10);
  stats.levels = {};
  stats.reflections = h.reflections;
  for (const k of ["vehicles", "bodies", "cameras"]) {
    for (const r of h[k]) stats.levels[`${k}:${r.name}`] = r.level;
  }
  document.getElementById("health-at").textContent = `at ${clockText(Date.now())}, once a second`;
  showWarnings(h);
  fillTable("vehicles", h.vehicles.map(v => [v.level, [[`${v.name} (sysid ${v.sysid})`],
    [v.link_up ? "up" : "DOWN", v.link_up ? "good" : "badv"],
    [v.ekf ?? "-", v.ekf === "using vision" ? "good" : v.ekf === "unknown" || v.ekf === null ? "warn" : "badv",
      v.ekf_detail || ""],
    [fmt(v.delay_ms, 1), "", v.delay_detail || ""], [rate(v.rate_hz, v.rate_configured_hz)], [String(v.sent)],
    [v.timesync_rtt_ms !== null ? `rtt ${fmt(v.timesync_rtt_ms, 1)} ms` : `${v.timesync_answered ?? 0} answered`],
    [v.signed ? "yes" : "no", v.signed ? "good" : "warn"], [fmt(v.latency_ms_p50, 1)], alerts(v)]]));
  fillTable("bodies", h.bodies.map(b => [b.level, [[b.name], [b.tracked ? "yes" : "NO", b.tracked ? "good" : "badv"],
    [rate(b.rate_hz, b.rate_configured_hz)], [b.tracked ? String(b.n_markers) : "-"],
    [b.tracked ? String(b.n_cameras) : "-"], [b.tracked ? fmt(b.residual_mm, 2) : "-"], alerts(b)]]));
  fillTable("cameras", h.cameras.map(c => {
    const dropped = Object.entries(c.dropped).map(([k, n]) => `${n} ${k.replaceAll("_", " ")}`).join(", ") || "none";
    const droppedWhy = Object.keys(c.dropped).map(k => h.drop_reasons[k] || k).join("; ");
    return [c.level, [[`${c.id} ${c.name}`], [c.state, c.state === "streaming" ? "good" : "badv"],
      [rate(c.fps, c.fps_configured)], [ago(c.last_seen_s_ago)], [fmt(c.latency_ms, 1)],
      [`${fmt(c.clock_offset_ms, 2)} (±${fmt(c.clock_uncertainty_us, 0)})`],
      [c.loss === null ? "-" : `${fmt(100 * c.loss, 1)}%`],
      [`${fmt(c.residual_px, 2)} (${fmt(c.residual_calibration_px, 2)})`], [fmt(c.shed_per_s, 0)],
      [dropped, "", droppedWhy], alerts(c)]];
  }));
  const s = h.server;
  const line = document.getElementById("server");
  line.textContent = `server: ${fmt(s.shed_per_s, 0)} frames/s shed, ${fmt(s.late_ticks_per_s, 0)} late ticks/s, ` +
    `output ${fmt(s.output_rate_hz, 0)} ticks/s`;  // its alerts are in the warnings above
  line.className = `row-${s.level}`;
}

// ------------------------------------------------------------------ a body's details (click it in the 3D view)

let selected = -1;
let lastBodies = [];

function rpyDeg([x, y, z, w]) {
  const roll = Math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y));
  const pitch = Math.asin(Math.max(-1, Math.min(1, 2 * (w * y - z * x))));
  const yaw = Math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z));
  return [roll, pitch, yaw].map(a => a * 180 / Math.PI);
}

function showBody() {
  const box = document.getElementById("bodyinfo");
  const b = lastBodies[selected];
  box.hidden = !b;
  if (!b) { stats.bodyInfo = null; return; }
  const hb = lastHealth?.bodies.find(x => x.name === b.name);
  const seeing = [...camViews.values()].filter(v => v.seen && v.seen.has(selected)).map(v => v.c.name);
  const lines = [`${b.name}: ${b.tracked ? "tracked" : "NOT tracked: " + (b.why || "")}`];
  if (b.tracked) {
    const [r, p, y] = rpyDeg(b.q);
    lines.push(`position ${b.p.map(v => fmt(v, 3)).join(", ")} m`,
      `roll ${fmt(r, 1)}, pitch ${fmt(p, 1)}, yaw ${fmt(y, 1)} deg`,
      `${b.n_markers} markers, ${b.n_cameras} cameras, fit ${fmt(b.residual_mm, 2)} mm`,
      b.nis ? `NIS position ${fmt(b.nis[0], 2)}, rotation ${fmt(b.nis[1], 2)} (about 1 when the filter is right)`
        : "NIS -");
  }
  if (hb) lines.push(`${fmt(hb.rate_hz, 0)} of ${fmt(hb.rate_configured_hz, 0)} ticks/s`);
  lines.push(`seen by: ${seeing.length ? seeing.join(", ") : "no camera"}`);
  for (const v of (lastHealth?.vehicles || []).filter(v => v.body === b.name)) {
    lines.push(`vehicle ${v.name}: ${v.level}, ${fmt(v.rate_hz, 0)} poses/s, EKF ${v.ekf ?? "-"}` +
      (v.delay_ms !== null ? `, delay ${fmt(v.delay_ms, 1)} ms` : ""));
  }
  box.replaceChildren(...lines.map(t => el("div", t)));
  stats.bodyInfo = lines;
}

function wire3D(canvas) {
  let down = null;
  canvas.addEventListener("pointerdown", e => { down = [e.clientX, e.clientY]; });
  canvas.addEventListener("pointerup", e => {
    if (!down || !scene3 || Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 5) return;  // a drag: orbiting
    selected = scene3.pick(e.clientX, e.clientY);
    showBody();
  });
  const preset = document.getElementById("preset");
  preset.onchange = () => { if (scene3 && preset.value) scene3.preset(preset.value); };
  stats.screenOf = name => scene3 && scene3.screenOf(scene3.bodies.findIndex(b => b.name === name));
}

// ------------------------------------------------------------------ replay controls

function send(obj) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj)); }

let seeking = false;
let lostShown = -1;  // marks drawn on the seek bar (the server counts them in lost_n)
function showLosses(r) {
  const box = document.getElementById("lost");
  box.replaceChildren(...r.lost.map(m => {
    const i = el("i");
    i.style.left = `${(100 * m.t_s / r.duration_s).toFixed(2)}%`;
    i.title = `${m.body} lost at ${fmt(m.t_s, 2)} s`;
    return i;
  }));
  lostShown = r.lost.length;
  stats.lost = r.lost;
}
function showReplay(r) {
  document.getElementById("replay").hidden = false;
  if (r.lost) showLosses(r);
  else if (r.lost_n !== undefined && r.lost_n !== lostShown) { lostShown = r.lost_n; send({ cmd: "losses" }); }
  for (const id of ["stepback", "stepfwd"]) document.getElementById(id).disabled = r.playing;
  stats.replayPos = r.t_s;
  const seek = document.getElementById("seek");
  seek.max = r.duration_s;
  if (!seeking) seek.value = r.t_s;
  document.getElementById("pos").textContent = `${fmt(r.t_s, 1)} / ${fmt(r.duration_s, 1)} s`;
  document.getElementById("play").innerHTML = r.playing ? "&#10074;&#10074;" : "&#9658;";
  document.getElementById("play").dataset.playing = r.playing ? "1" : "";
}

function wireControls() {
  document.getElementById("play").onclick = e => send({ cmd: e.currentTarget.dataset.playing ? "pause" : "play" });
  const seek = document.getElementById("seek");
  seek.oninput = () => { seeking = true; };
  seek.onchange = () => { seeking = false; send({ cmd: "seek", t_s: Number(seek.value) }); };
  document.getElementById("speed").onchange = e => send({ cmd: "speed", x: Number(e.target.value) });
  document.getElementById("stepback").onclick = () => send({ cmd: "step", frames: -1 });
  document.getElementById("stepfwd").onclick = () => send({ cmd: "step", frames: 1 });
  document.getElementById("rays").onchange = e => {
    if (scene3) scene3.rayCamera = e.target.value || null;
    send({ cmd: "rays", camera: e.target.value ? Number(e.target.value) : null });  // the server sends only those
  };
}

// ------------------------------------------------------------------ connection

function clockText(ms) { return new Date(ms).toTimeString().slice(0, 8); }

// what a tab shows of the arena: built on the first scene, built again when a scene with another id comes
function buildArena(msg) {
  sceneMsg = msg;
  const replay = msg.mode === "replay";
  document.getElementById("source").textContent = replay ? `replay of ${msg.source}` : msg.source;
  calibReplay(replay);
  lostShown = -1;
  document.getElementById("lost").replaceChildren();
  initRecord(msg, send);
  if (scene3) { scene3.load(msg); stats.rebuilds++; } else scene3 = new Arena3D(document.getElementById("view3d"), msg);
  document.getElementById("camgrid").replaceChildren();
  camViews.clear();
  resetStationTools();
  stats.blobs = {};
  const rays = document.getElementById("rays");
  rays.replaceChildren(rays.options[0]);
  rays.value = "";
  const preset = document.getElementById("preset");
  preset.replaceChildren(...["", "top", "front", ...msg.cameras.map(c => `camera ${c.id}`)].map(v => {
    const o = el("option", v || "view...");
    o.value = v;
    return o;
  }));
  selected = -1;
  showBody();
  for (const c of msg.cameras) {
    camViews.set(c.id, new CameraView(c, replay));
    const o = el("option", `camera ${c.id} (${c.name})`);
    o.value = String(c.id);
    rays.append(o);
  }
  stats.cameraViews = camViews.size;
  stats.frusta = scene3.frusta;
  stats.volume = scene3.volume;
  stats.sceneId = msg.scene_id;
}

function onScene(msg) {
  stats.scenes++;
  if (!sceneMsg || msg.scene_id !== sceneMsg.scene_id) { buildArena(msg); return; }
  // the same arena again (a reconnect): only the masks may have changed meanwhile
  sceneMsg = msg;
  for (const c of msg.cameras) {
    const v = camViews.get(c.id);
    if (v && JSON.stringify(v.c.mask) !== JSON.stringify(c.mask)) {
      v.c.mask = c.mask;
      v.dim = null;
      v.mask = null;
      if (c.mask && c.mask.mask_png) { v.mask = new Image(); v.mask.src = c.mask.mask_png; }
    }
  }
}

function onState(msg) {
  stats.states++;
  if (scene3) scene3.update(msg);
  for (const v of msg.cameras || []) camViews.get(v.id)?.draw(v);  // camera_view_rate_hz of the updates carry them
  lastBodies = msg.bodies;
  if (selected >= 0) showBody();
  if (msg.replay) showReplay(msg.replay);
}

// live or not: every message of the stream counts as data; a closed socket or STALE_MS of silence is not live
let lastDataMs = null;
let full = null;  // {reason, tries}: the server refused this tab (console.max_clients), until a scene comes
const FULL_RETRY_MS = 5000;
let rateMark = { ms: Date.now(), states: 0 };
function setLive() {
  const conn = document.getElementById("conn");
  const open = ws && ws.readyState === WebSocket.OPEN;
  const stale = !open || lastDataMs === null || Date.now() - lastDataMs > STALE_MS;
  const since = lastDataMs === null ? "no data yet" : `no data since ${clockText(lastDataMs)}`;
  const rate = stats.updatesPerS === null ? "" : `${fmt(stats.updatesPerS, 0)} updates/s`;
  const wanted = sceneMsg?.update_rate_hz;
  const slow = wanted && stats.updatesPerS !== null && stats.updatesPerS < 0.9 * wanted;
  stats.stale = stale;
  stats.staleText = stale ? since : "";
  document.body.classList.toggle("stale", stale);
  for (const e of document.querySelectorAll(".stale-note")) e.textContent = stats.staleText;
  conn.textContent = stale && full ? `refused: ${full.reason} (tried ${full.tries} times; next try in ` +
    `${FULL_RETRY_MS / 1000} s)` : stale ? (open ? `connected, ${since}` : `disconnected, retrying; ${since}`) : "live";
  conn.className = stale ? "bad" : "ok";
  const badge = document.getElementById("badge3d");
  badge.textContent = stale ? since : (rate ? `live, ${rate}` : "live") + (slow ? ` (configured ${wanted})` : "");
  badge.className = stale ? "badv" : slow ? "warn" : "good";
}

function tickLive() {
  const now = Date.now();
  if (now - rateMark.ms >= RATE_WINDOW_MS) {
    stats.updatesPerS = (stats.states - rateMark.states) * 1000 / (now - rateMark.ms);
    rateMark = { ms: now, states: stats.states };
  }
  setLive();
}

// a refusal the server sent ({"type": "error"}): shown in the header until the next one, with its time
let lastRefusal = null;
function showRefusal(text) {
  lastRefusal = text;
  const n = document.getElementById("notice");
  n.textContent = `${clockText(Date.now())} refused: ${text}`;
  n.title = text;
  n.hidden = false;
  stats.refusal = text;
}

function connect() {
  const url = new URL("ws", location.href);
  url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
  if (token) url.searchParams.set("token", token);
  ws = new WebSocket(url);
  ws.onopen = () => {
    const rays = document.getElementById("rays").value;
    if (rays) send({ cmd: "rays", camera: Number(rays) });
    if (document.hidden) send({ cmd: "views", on: false });
    setLive();
  };
  ws.onclose = ev => {
    // 1013: the console serves console.max_clients tabs and refused this one; its reason came as an error first
    if (ev.code === 1013) {
      full = { reason: lastRefusal || ev.reason || "the console is full", tries: (full?.tries || 0) + 1 };
      stats.full = full;
    }
    setLive();
    setTimeout(connect, ev.code === 1013 ? FULL_RETRY_MS : 1000);
  };
  ws.onmessage = e => {
    const t0 = performance.now();
    handle(e);
    const ms = performance.now() - t0;  // the page's own cost per message (stats: mean and max)
    stats.handled = (stats.handled || 0) + 1;
    stats.handleMsTotal = (stats.handleMsTotal || 0) + ms;
    stats.handleMsMax = Math.max(stats.handleMsMax || 0, ms);
  };
}

// one message of the stream: every message counts as data (the page is live)
function handle(e) {
  const msg = JSON.parse(e.data);
  if (msg.type !== "error") lastDataMs = Date.now();  // a refusal is no data: a refused tab must not look live
  if (msg.type === "scene") { full = null; stats.full = null; onScene(msg); }
  else if (msg.type === "state") onState(msg);
  else if (msg.type === "health") showHealth(msg.health);
  else if (msg.type === "replay") {  // an answer to a control: sent once it is done (a seek reached its target)
    stats.replayReplies = (stats.replayReplies || 0) + 1;
    stats.replayReply = msg.t_s;
    showReplay(msg);
  }
  else if (msg.type === "still" || msg.type === "mask") onStationMessage(msg, camViews);
  else if (msg.type === "error") { stats.errors.push(msg.error); showRefusal(msg.error); onStationMessage(msg, camViews); }
  if (msg.type === "health" || msg.type === "record") recordMessage(msg);
  if (msg.type === "health" || msg.type === "pose_written") monitorMessage(msg);
  if (msg.type === "calib" || msg.type === "calib_reply" || msg.type === "error") calibMessage(msg, send);
}

wireControls();
wire3D(document.getElementById("view3d"));
initStationTools(send, stats);
initMonitor(send);
// a hidden tab draws nothing: the server builds no camera views for it until it is shown again
document.addEventListener("visibilitychange", () => send({ cmd: "views", on: !document.hidden }));
connect();
setInterval(tickLive, 250);
