// The calibration assistant's panel (console/calibration.py): while a wand wave is recorded, each camera's
// image coverage as a heat map and the frames each camera pair shares, ENOUGH or what is missing, and the
// Solve button with the wand solve's result. Messages: calib (the state), calib_reply (a solve started, an
// apply done), error (a refused command: "solve: ...", "apply: ...", "ground: ...", "wave: ..."). The panel is
// made on the first calib message. On a running fusion server (serve, demo: calib.live,
// console/live_calibration.py) it also gathers the wave ("gather wave"), shows the solve's residuals next to
// the running calibration's on the same wand frames, applies the solve after a confirmation, and finds the
// ground frame ("set ground") and applies the floor transform the same way.

const HEAT_WIDTH_PX = 200;
let panel = null;
let sendFn = null;
let replay = false;
let live = false;  // a running fusion server: gather, apply, ground
let gathering = false;
let lastApplyRefusal = null;
const GROUND_NOTE = "the console watches it for 2 s, finds it and shows the floor transform";  // a replay shows the panel only once the recording gave wand frames (not for a flight)

// app.js says so with each scene
export function calibReplay(on) { replay = on; }

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

function num(x, d) { return x === null || x === undefined ? "-" : Number(x).toFixed(d); }

function stats() {
  const s = window.visionposConsole || (window.visionposConsole = {});
  if (!s.calib) s.calib = { messages: 0, enough: null, cameras: 0, pairs: 0, heatCells: 0, solve: null, refused: [] };
  return s.calib;
}

function build() {
  const sec = el("section");
  sec.id = "calib";
  sec.innerHTML = `
    <div class="bar">Calibration (wand wave)
      <span id="calib-verdict" class="calib-verdict">-</span>
      <button id="calib-solve" title="run the wand solve on the frames gathered so far">Solve</button>
      <span id="calib-out" class="calib-note"></span>
    </div>
    <ul id="calib-missing"></ul>
    <div id="calib-heat"></div>
    <h2>Camera pairs: time steps seeing the wand together</h2>
    <table id="calib-pairs"><thead><tr><th>pair</th><th>shared</th></tr></thead><tbody></tbody></table>
    <div id="calib-result"></div>`;
  document.querySelector("main").append(sec);
  sec.querySelector("#calib-solve").onclick = () => sendFn && sendFn({ cmd: "solve" });
  if (live) {
    const bar = sec.querySelector(".bar");
    const wave = el("button", "gather wave");
    wave.id = "calib-wave";
    wave.title = "gather every frame the stations send as the wand wave (again: start over)";
    wave.onclick = () => sendFn && sendFn({ cmd: "wave", on: !gathering });
    const ground = el("button", "set ground");
    ground.id = "calib-ground";
    ground.title = `lay the L-frame (ground frame) on the floor, still, and press: ${GROUND_NOTE}`;
    ground.onclick = () => sendFn && sendFn({ cmd: "ground" });
    bar.insertBefore(wave, sec.querySelector("#calib-solve"));
    bar.append(ground);
    sec.append(el("div", undefined, "calib-apply"));
    sec.lastChild.id = "calib-apply";
    sec.append(el("div", undefined, "calib-apply"));
    sec.lastChild.id = "calib-groundbox";
  }
  return sec;
}

function heat(cam, th) {
  const box = el("div", undefined, "calib-cam");
  const cover = Math.round(100 * cam.coverage);
  const ok = cam.labelled >= th.camera_frames && cam.coverage >= th.coverage;
  box.append(el("div", `${cam.name}: ${cam.labelled} wand frames, ${cover} % covered`, ok ? "good" : "warn"));
  const c = el("canvas");
  c.width = HEAT_WIDTH_PX;
  c.height = Math.round(HEAT_WIDTH_PX * cam.height / cam.width);
  const g = c.getContext("2d");
  const rows = cam.grid.length, cols = cam.grid[0].length;
  const w = c.width / cols, h = c.height / rows;
  let lit = 0;
  for (let r = 0; r < rows; r++) {
    for (let k = 0; k < cols; k++) {
      const n = cam.grid[r][k];
      // a cell turns green once it counts; before that it warms up from dark
      if (n >= th.cell_markers) {
        const a = Math.min(1, 0.35 + 0.65 * Math.log10(n) / 3);
        g.fillStyle = `rgba(90, 220, 110, ${a})`;
        lit++;
      } else g.fillStyle = n > 0 ? "#6a5520" : "#1a1d22";
      g.fillRect(k * w + 1, r * h + 1, w - 2, h - 2);
    }
  }
  stats().heatCells += lit;
  box.append(c);
  return box;
}

function showResult(div, solve) {
  div.replaceChildren();
  if (solve.running) { div.append(el("p", `solving ${solve.frames} frames...`, "warn")); return; }
  if (solve.error) {
    div.append(el("h2", "Solve failed"));
    div.append(el("pre", solve.error, "badv"));
    return;
  }
  const r = solve.result;
  if (!r) return;
  div.append(el("h2", `Result: written to ${r.out} (${r.time_steps} time steps, ${num(r.seconds, 1)} s)`));
  const t = el("table");
  t.id = "calib-result-table";
  t.innerHTML = "<thead><tr><th>camera</th><th>rms px</th><th>max px</th><th>views</th>" +
    "<th>clock offset ms</th></tr></thead>";
  const body = el("tbody");
  for (const c of r.cameras) {
    const tr = el("tr");
    for (const v of [c.name, num(c.rms_px, 3), num(c.max_px, 2), c.views, num(c.offset_ms, 2)]) tr.append(el("td", String(v)));
    body.append(tr);
  }
  t.append(body);
  div.append(t);
  div.append(el("p", `wand length A-C: error ${num(r.wand_ac_mean_err_mm, 3)} mm, std ${num(r.wand_ac_std_mm, 3)} mm`,
    "calib-wand"));
  const warn = el("ul", undefined, "calib-warnings");
  for (const w of r.warnings) warn.append(el("li", w));
  if (r.warnings.length) div.append(warn);
}

function confirmSend(text, msg) {
  if (window.confirm(text)) sendFn && sendFn(msg);
}

// the solve against the running calibration on the same wand frames, and the apply button
function showCompare(s) {
  const div = panel.querySelector("#calib-apply");
  const r = s.solve.result;
  div.replaceChildren();
  if (s.applied) div.append(el("p", `applied: the ${s.applied.what}, written to ${s.applied.file} (the old file: ` +
    `${s.applied.backup})`, "good"));
  if (!r || !r.current) return;
  div.append(el("h2", "Solve against the running calibration, on the same wand frames"));
  const t = el("table");
  t.id = "calib-compare";
  t.innerHTML = "<thead><tr><th>camera</th><th>running px RMS</th><th>solve px RMS</th><th>moves it deg</th>" +
    "<th>moves it mm</th></tr></thead>";
  const body = el("tbody");
  r.current.cameras.forEach((c, i) => {
    const tr = el("tr");
    const n = r.new.cameras[i], m = r.moved[i];
    for (const v of [c.name, num(c.rms_px, 3), num(n.rms_px, 3), num(m.rotation_deg, 3), num(m.shift_mm, 1)]) {
      tr.append(el("td", String(v)));
    }
    body.append(tr);
  });
  const all = el("tr");
  for (const v of ["all", num(r.current.rms_px, 3), num(r.new.rms_px, 3), "", ""]) all.append(el("td", String(v)));
  body.append(all);
  const wand = el("tr");
  for (const v of ["wand A-C error mm", num(r.current.wand_ac_err_mm, 2), num(r.new.wand_ac_err_mm, 2), "", ""]) {
    wand.append(el("td", String(v)));
  }
  body.append(wand);
  t.append(body);
  div.append(t);
  if (r.refused) { div.append(el("p", `not applicable: ${r.refused}`, "badv")); return; }
  if (s.applied_results.solve) return;
  const b = el("button", "apply to the running server");
  b.id = "calib-apply-button";
  b.onclick = () => confirmSend("Apply this solve to the running server? Fusion switches to the new camera poses " +
    "between two frames, and the arena file it started with is rewritten (the old one kept beside it).",
    { cmd: "apply_calibration" });
  div.append(b);
}

function showGround(s) {
  const div = panel.querySelector("#calib-groundbox");
  const g = s.ground;
  div.replaceChildren();
  if (g.state === "gathering") div.append(el("p", `ground frame: ${GROUND_NOTE}...`, "warn"));
  else if (g.state === "solving") div.append(el("p", "ground frame: finding it...", "warn"));
  else if (g.state === "failed") div.append(el("pre", `ground frame not found: ${g.error}`, "badv"));
  if (g.state !== "found") return;
  const r = g.result;
  div.append(el("h2", "Ground frame found: the floor transform"));
  const p = el("p", `tilt ${num(r.tilt_deg, 2)} deg, turn ${num(r.rotation_deg, 2)} deg, shift ${num(r.shift_mm, 1)} ` +
    `mm; layout fit ${num(r.fit_mm, 2)} mm (${r.frames} frames); camera heights after: ` +
    Object.entries(r.heights_m).map(([k, v]) => `${k} ${num(v, 2)} m`).join(", "));
  p.id = "calib-ground-result";
  div.append(p);
  if (s.applied_results.ground) return;
  const b = el("button", "apply the floor");
  b.id = "calib-ground-apply";
  b.onclick = () => confirmSend("Move the running world onto this floor? Every camera pose changes, and the arena " +
    "file the server started with is rewritten (the old one kept beside it).", { cmd: "apply_ground" });
  div.append(b);
}

function show(s) {
  const st = stats();
  live = !!s.live;
  gathering = !!s.gathering;
  if (!panel && replay && !s.cameras.some(c => c.labelled > 0) && !s.solve.running && !s.solve.result) {
    st.hidden = true;  // a flight recording: no wand, no panel
    return;
  }
  st.hidden = false;
  if (!panel) panel = build();
  st.messages++;
  st.enough = s.enough;
  st.cameras = s.cameras.length;
  st.pairs = s.pairs.length;
  st.heatCells = 0;
  st.solve = s.solve;
  st.framesKept = s.frames_kept;
  // a running server's panel before any wave: its bar alone (the coverage lists would only say "0 frames")
  panel.classList.toggle("calib-idle", live && !gathering && s.frames_kept === 0);
  const v = panel.querySelector("#calib-verdict");
  v.textContent = s.enough ? "ENOUGH" : "not yet";
  v.className = "calib-verdict " + (s.enough ? "enough" : "notyet");
  const solve = panel.querySelector("#calib-solve");
  solve.disabled = s.solve.running || !s.solvable;
  solve.title = s.solvable ? "run the wand solve on the frames gathered so far"
    : "not yet: the solver needs 100 wand frames per camera and 100 time steps in two cameras";
  const full = s.frames_over ? `; full: ${s.frames_over} later frames not kept` : "";
  panel.querySelector("#calib-out").textContent = `${s.frames_kept} frames, ${s.steps} time steps; ` +
    `Solve writes ${s.out}${full}`;
  const missing = panel.querySelector("#calib-missing");
  missing.replaceChildren(...s.missing.map(m => el("li", m)));
  const th = s.thresholds;
  panel.querySelector("#calib-heat").replaceChildren(...s.cameras.map(c => heat(c, th)));
  const names = new Map(s.cameras.map(c => [c.id, c.name]));
  panel.querySelector("#calib-pairs tbody").replaceChildren(...s.pairs.map(p => {
    const tr = el("tr");
    tr.append(el("td", `${names.get(p.a)} - ${names.get(p.b)}`));
    tr.append(el("td", String(p.frames), p.frames >= th.pair_frames ? "good" : "warn"));
    return tr;
  }));
  showResult(panel.querySelector("#calib-result"), s.solve);
  if (live) {
    const w = panel.querySelector("#calib-wave");
    w.textContent = gathering ? "stop the wave" : "gather wave";
    showCompare(s);
    showGround(s);
    const note = el("p", lastApplyRefusal || "", "badv");
    note.id = "calib-refusal";
    panel.querySelector("#calib-groundbox").append(note);
    st.applied = s.applied;
    st.ground = s.ground.state;
  }
}

// app.js hands every calib, calib_reply and error message here, with its send()
export function calibMessage(msg, send) {
  sendFn = send;
  if (msg.type === "calib") show(msg.calib);
  else if (msg.type === "error" && typeof msg.error === "string" && /^(solve|apply|ground|wave):/.test(msg.error)) {
    stats().refused.push(msg.error);
    if (/^(apply|ground):/.test(msg.error)) {  // kept under the apply buttons until the next one
      lastApplyRefusal = `${new Date().toLocaleTimeString()} refused: ${msg.error}`;
      const box = panel && panel.querySelector("#calib-refusal");
      if (box) box.textContent = lastApplyRefusal;
      return;
    }
    if (panel) {
      const div = panel.querySelector("#calib-result");
      div.replaceChildren(el("p", msg.error, "badv"));
    }
  }
}
