// The camera monitor's corrections in the health panel (health.camera_monitor, fusion/camera_monitor.py): per
// corrected camera how far its pose moved, and "write to arena file", which asks the operator first and then
// sends {"cmd": "write_pose", "camera": id} (console/arena_file.py). Messages: health, pose_written, error
// ("write pose: ...", shown in the header by app.js).

let sendFn = null;

function stats() {
  const s = window.visionposConsole || (window.visionposConsole = {});
  if (!s.monitor) s.monitor = { rows: 0, written: null };
  return s.monitor;
}

export function initMonitor(send) { sendFn = send; }

function row(cid, c) {
  const li = document.createElement("li");
  const moved = c.corrected_deg === undefined ? "" : `, ${c.corrected_deg.toFixed(2)} deg and ` +
    `${c.corrected_mm.toFixed(1)} mm since it moved`;
  li.textContent = `camera ${cid} (${c.name}): pose corrected ${c.corrections} time(s)${moved}` +
    (c.agrees_again ? ", agrees again " : " ");
  const b = document.createElement("button");
  b.textContent = "write to arena file";
  b.dataset.camera = cid;
  b.onclick = () => {
    if (window.confirm(`Write camera ${cid} (${c.name})'s corrected pose into the arena file the server ` +
                       "started with? The old file is kept beside it as a backup.")) {
      sendFn({ cmd: "write_pose", camera: Number(cid) });
    }
  };
  li.append(b);
  return li;
}

export function monitorMessage(msg) {
  const box = document.getElementById("monitor");
  if (msg.type === "health") {
    const cams = msg.health.camera_monitor?.cameras || {};
    const rows = Object.entries(cams).filter(([, c]) => c.corrections > 0 && c.state !== "not_solvable");
    // rebuilt only when its text changes: a button under the pointer stays put
    const items = rows.map(([cid, c]) => row(cid, c));
    const key = items.map(li => li.textContent).join("\n");
    if (box.dataset.key !== key) { box.dataset.key = key; box.replaceChildren(...items); }
    stats().rows = rows.length;
  } else if (msg.type === "pose_written") {
    const note = document.getElementById("monitor-note");
    note.textContent = `camera ${msg.camera}'s pose written to ${msg.file} (the old file: ${msg.backup})`;
    stats().written = msg;
  }
}
