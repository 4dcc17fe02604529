// The record button in the header (console/recording.py): start and stop a recording of the running server,
// with its file name, size and duration while it records, and the saved file after a stop. Shown only where the
// server can record (scene.can_record: not in a replay or `visionpos record`). Messages: health (its
// "recording", once a second), record (the answer to a start or stop, to every tab), error ("record: ...").

let sendFn = null;
let recording = null;

function stats() {
  const s = window.visionposConsole || (window.visionposConsole = {});
  if (!s.record) s.record = { shown: false, recording: null, stopped: null };
  return s.record;
}

function size(bytes) {
  return bytes >= 1e6 ? `${(bytes / 1e6).toFixed(1)} MB` : `${Math.round(bytes / 1e3)} kB`;
}

function show(rec, stopped) {
  recording = rec;
  const st = stats();
  st.recording = rec;
  const button = document.getElementById("rec");
  const info = document.getElementById("recinfo");
  button.textContent = rec ? "stop recording" : "record";
  button.className = rec ? "recording" : "";
  if (rec) info.textContent = `recording ${rec.file}, ${size(rec.bytes)}, ${rec.duration_s.toFixed(0)} s`;
  else if (stopped) info.textContent = `saved ${stopped.file}, ${size(stopped.bytes)}`;
  info.title = rec ? rec.path : stopped ? stopped.path : "";
  if (stopped) st.stopped = stopped;
}

// app.js, with each scene: the button only where the server can record
export function initRecord(scene, send) {
  sendFn = send;
  const box = document.getElementById("recbox");
  box.hidden = !scene.can_record;
  stats().shown = !box.hidden;
  document.getElementById("rec").onclick = () => sendFn({ cmd: "record", on: !recording });
}

export function recordMessage(msg) {
  if (msg.type === "health") show(msg.health.recording || null, null);
  else if (msg.type === "record") show(msg.recording, msg.stopped);
}
