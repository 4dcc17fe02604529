// Station tools of a camera view (console/stills.py): a still image from the station under the blob overlay with
// its background level read out, and ignore rectangles drawn on the view and saved to the station's config.
// app.js calls stationTools(view, box) once per CameraView, drawStationLayer(view, g) under the blobs on every
// draw, and onStationMessage(msg, camViews) for {"type": "still" | "mask"} answers and errors.

let send = () => {};
let pending = null;  // camera id of the newest still/mask command, for an {"type": "error"} answer
const shown = {};    // what the browser tests read: camera id -> {background, width, height, loaded}

export function initStationTools(sendFn, stats) {
  send = sendFn;
  stats.stills = shown;
}

// another arena: the old cameras' stills and pending answers are gone with their views
export function resetStationTools() {
  pending = null;
  for (const k of Object.keys(shown)) delete shown[k];
}

function button(text, title, onclick) {
  const b = document.createElement("button");
  b.textContent = text;
  b.title = title;
  b.onclick = onclick;
  return b;
}

export function stationTools(view, box) {
  const id = view.c.id;
  view.still = null;          // HTMLImageElement of the newest still image
  view.drafts = null;         // ignore rectangles being edited (camera pixels), null when not editing
  view.drag = null;
  const bar = document.createElement("div");
  bar.className = "stationtools";
  view.stationStatus = document.createElement("span");
  view.stationStatus.id = `still-status-${id}`;
  const drawBtn = view.drawBtn = button("draw mask", "drag rectangles on the view that the station must not search", () => {
    view.drafts = view.drafts ? null : (view.c.mask?.ignore || []).map(r => r.slice());
    drawBtn.classList.toggle("on", !!view.drafts);
    view.canvas.style.cursor = view.drafts ? "crosshair" : "";
  });
  bar.append(
    button("still image", "ask the station for an image of what it sees now", () => {
      pending = id;
      view.stationStatus.textContent = "asking the station...";
      send({ cmd: "still", camera: id });
    }),
    drawBtn,
    button("undo", "remove the last ignore rectangle", () => { if (view.drafts) view.drafts.pop(); }),
    button("save mask", "send the ignore rectangles to the station; it applies and saves them", () => {
      const ignore = view.drafts || view.c.mask?.ignore || [];
      pending = id;
      view.stationStatus.textContent = "saving the mask...";
      send({ cmd: "mask", camera: id, ignore });
    }),
    view.stationStatus);
  box.append(bar);
  const toCamera = e => {
    const r = view.canvas.getBoundingClientRect();
    const x = (e.clientX - r.left) / r.width * view.c.width, y = (e.clientY - r.top) / r.height * view.c.height;
    return [Math.min(Math.max(Math.round(x), 0), view.c.width), Math.min(Math.max(Math.round(y), 0), view.c.height)];
  };
  view.canvas.addEventListener("mousedown", e => { if (view.drafts) view.drag = [toCamera(e), toCamera(e)]; });
  view.canvas.addEventListener("mousemove", e => { if (view.drag) view.drag[1] = toCamera(e); });
  view.canvas.addEventListener("mouseup", () => {
    if (!view.drag) return;
    const [[xa, ya], [xb, yb]] = view.drag;
    view.drag = null;
    const r = [Math.min(xa, xb), Math.min(ya, yb), Math.max(xa, xb), Math.max(ya, yb)];
    if (r[2] > r[0] && r[3] > r[1]) view.drafts.push(r);
  });
}

// the health panel's "mask these": the camera's ignore rectangles plus the proposed ones, in draw mode for the
// operator to check; nothing reaches the station until "save mask"
export function proposeMask(view, rects) {
  const have = view.drafts || (view.c.mask?.ignore || []).map(r => r.slice());
  const key = r => r.join(",");
  view.drafts = have.concat(rects.filter(r => !have.some(h => key(h) === key(r))).map(r => r.slice()));
  view.canvas.dataset.drafts = JSON.stringify(view.drafts);  // what the browser tests read
  view.drawBtn.classList.add("on");
  view.canvas.style.cursor = "crosshair";
  view.stationStatus.textContent = `${view.drafts.length} rectangles drawn: check them, then "save mask"`;
  view.stationStatus.className = "warn";
  view.canvas.scrollIntoView({ block: "nearest" });
}

// under the blobs: the still image, then the rectangles being drawn
export function drawStationLayer(view, g) {
  const s = view.scale;
  if (view.still && view.still.complete && view.still.naturalWidth) {
    g.globalAlpha = 0.85;
    g.drawImage(view.still, 0, 0, view.canvas.width, view.canvas.height);
    g.globalAlpha = 1;
  }
  const rects = (view.drafts || []).concat(view.drag ? [[...view.drag[0], ...view.drag[1]]] : []);
  g.setLineDash([4, 3]);
  g.strokeStyle = "#f66";
  for (const [xa, ya, xb, yb] of rects) {
    g.strokeRect(Math.min(xa, xb) * s + 0.5, Math.min(ya, yb) * s + 0.5, Math.abs(xb - xa) * s, Math.abs(yb - ya) * s);
  }
  g.setLineDash([]);
}

export function onStationMessage(msg, camViews) {
  onStationAnswer(msg, camViews);
  for (const v of camViews.values()) if (v.stationStatus) v.stationStatus.title = v.stationStatus.textContent;
}

function onStationAnswer(msg, camViews) {
  if (msg.type === "error") {
    const v = pending !== null && camViews.get(pending);
    if (v) v.stationStatus.textContent = msg.error;
    return;
  }
  const v = camViews.get(msg.camera);
  if (!v) return;
  if (msg.type === "still") {
    if (msg.error) { v.stationStatus.textContent = msg.error; return; }
    const img = new Image();
    img.onload = () => { shown[msg.camera].loaded = true; };
    img.src = msg.jpeg;
    v.still = img;
    shown[msg.camera] = { background: msg.background, width: msg.width, height: msg.height, loaded: false };
    v.stationStatus.textContent = msg.hint;
    v.stationStatus.className = msg.background < 20 ? "good" : "warn";
  } else if (msg.type === "mask") {
    v.stationStatus.textContent = (msg.ok ? (msg.saved ? "mask saved: " : "mask applied, not saved: ") : "mask refused: ")
      + (msg.text || "");
    v.stationStatus.className = msg.saved ? "good" : "warn";
    if (msg.ok) {
      v.c.mask = msg.mask;
      v.mask = null;   // the station's mask image no longer tells the whole story: the rectangles do
      v.dim = null;
      v.drafts = null;
      v.drawBtn.classList.remove("on");
      v.canvas.style.cursor = "";
    }
  }
}
