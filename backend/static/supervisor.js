// CloudTrack supervisor page: the operator's console per vehicle. The newest keyframe with the tracked and
// candidate boxes, the state and why, search progress and coverage, the candidate awaiting a decision (its
// crop with the box drawn) with Confirm / Reject, a map drawn from the positions themselves (no internet
// needed; an optional tile layer from `[supervisor] map_tiles`) with the POD map and its legend, and the
// finds, which stay. Above the vehicles, the fleet: per mission one map with every vehicle's part, track and
// position in its colour and named by its id over the mission's merged coverage or POD map, a legend (id,
// colour, state, coverage of its part), and one queue of every vehicle's candidates, newest first.
// The token is a bearer token like the API's; it lives in this tab's sessionStorage only. Live updates are
// Server-Sent Events read with fetch() so the token travels in a header, never in a URL (or a proxy log).
// Everything that came from a vehicle or a VLM is inserted as text, never as HTML.
"use strict";

const TOKEN_KEY = "cloudtrack.supervisor_token";
const LIVE_S = 2; // a keyframe older than this is marked "not live"
const SVG = "http://www.w3.org/2000/svg";
const $ = (selector, root = document) => root.querySelector(selector);
let token = sessionStorage.getItem(TOKEN_KEY) || "";
let mapTiles = "";
const vehicles = new Map(); // vehicle id -> { view, receivedAt }
let missions = []; // the snapshot's missions: each one's merged map
let fleetTimer = null;
let stream = null;
const images = new Map(); // image URL -> object URL of the fetched image ("" while fetching)

function authHeaders(extra = {}) {
  return { Authorization: `Bearer ${token}`, ...extra };
}

function setConnection(status) {
  const badge = $("#connection");
  badge.dataset.status = status;
  badge.textContent = status;
}

function showLogin(message = "") {
  stream?.abort();
  stream = null;
  token = "";
  sessionStorage.removeItem(TOKEN_KEY);
  $("#login").hidden = false;
  $("#logout").hidden = true;
  $("#login-error").textContent = message;
  setConnection("offline");
}

async function login(event) {
  event.preventDefault();
  token = $("#token").value.trim();
  const response = await fetch("/supervisor/api/state", { headers: authHeaders() });
  if (response.status === 401 || response.status === 403) {
    showLogin("That token is not accepted.");
    return;
  }
  sessionStorage.setItem(TOKEN_KEY, token);
  $("#login").hidden = true;
  $("#login-error").textContent = "";
  $("#token").value = "";
  $("#logout").hidden = false;
  renderAll(await response.json());
  connect();
}

// --- live updates -------------------------------------------------------------------------------

async function connect(delayMs = 1000) {
  stream = new AbortController();
  const signal = stream.signal;
  try {
    const response = await fetch("/supervisor/events", { headers: authHeaders(), signal });
    if (response.status === 401 || response.status === 403) {
      showLogin("Your token is no longer accepted.");
      return;
    }
    if (!response.ok || !response.body) throw new Error(`HTTP ${response.status}`);
    setConnection("live");
    delayMs = 1000;
    const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buffer += value;
      let end;
      while ((end = buffer.indexOf("\n\n")) >= 0) {
        handleMessage(buffer.slice(0, end));
        buffer = buffer.slice(end + 2);
      }
    }
    // The server ends every stream after a while (see backend/routers/supervisor.py): open the next one.
    if (!signal.aborted) connect();
    return;
  } catch (error) {
    if (signal.aborted) return;
  }
  if (signal.aborted) return;
  setConnection("reconnecting");
  setTimeout(() => connect(Math.min(delayMs * 2, 10000)), delayMs);
}

function handleMessage(block) {
  let kind = "message";
  const data = [];
  for (const line of block.split("\n")) {
    if (line.startsWith(":")) continue; // keep-alive comment
    if (line.startsWith("event:")) kind = line.slice(6).trim();
    else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
  }
  if (!data.length) return;
  const body = JSON.parse(data.join("\n"));
  if (kind === "state") renderAll(body);
  else if (kind === "vehicle") renderVehicle(body);
  else if (kind === "fleet") {
    missions = body.missions || [];
    scheduleFleet();
    // The cards that draw their mission's merged map under their part.
    for (const { view } of vehicles.values()) {
      const card = document.querySelector(`section.vehicle[data-vehicle="${CSS.escape(view.id)}"]`);
      if (card && view.on_mission_map) renderMap(card, view);
    }
  }
  else if (kind === "ages") {
    // Reports that changed nothing else: only "last report" becomes young again.
    for (const [id, age] of Object.entries(body)) {
      const known = vehicles.get(id);
      if (known) {
        // The keyframe and the candidate aged meanwhile: kept, not reset with the report's age.
        const extra = (performance.now() - known.receivedAt) / 1000;
        if (known.view.keyframe) known.view.keyframe.age_s += extra;
        for (const candidate of known.view.candidates) candidate.age_s += extra;
        known.view.age_s = age;
        known.receivedAt = performance.now();
      }
    }
    tick();
  }
}

// --- rendering ------------------------------------------------------------------------------------

function formatAge(seconds) {
  if (seconds < 60) return `${Math.round(seconds)} s ago`;
  if (seconds < 3600) return `${Math.floor(seconds / 60)} min ${Math.round(seconds % 60)} s ago`;
  return `${(seconds / 3600).toFixed(1)} h ago`;
}

function plural(count, noun) {
  return `${count} ${noun}${count === 1 ? "" : "s"}`;
}

function formatPosition(position, sigma) {
  if (!position) return "position unknown";
  const text = `${position.lat.toFixed(6)}, ${position.lon.toFixed(6)}`;
  if (sigma === undefined) return text;
  return sigma === null ? `${text} (± ? m)` : `${text} (± ${sigma.toFixed(1)} m)`;
}

function formatTime(unix) {
  const date = new Date(unix * 1000);
  return `${date.toISOString().slice(0, 19).replace("T", " ")} UTC`;
}

function svg(tag, attributes = {}, parent = null) {
  const node = document.createElementNS(SVG, tag);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, value);
  if (parent) parent.appendChild(node);
  return node;
}

function renderAll(snapshot) {
  mapTiles = snapshot.map_tiles || "";
  missions = snapshot.missions || [];
  const seen = new Set(snapshot.vehicles.map((v) => v.id));
  for (const card of document.querySelectorAll("section.vehicle")) {
    if (!seen.has(card.dataset.vehicle)) {
      card.remove();
      vehicles.delete(card.dataset.vehicle);
    }
  }
  for (const vehicle of snapshot.vehicles) renderVehicle(vehicle);
  $("#no-vehicles").hidden = snapshot.vehicles.length > 0;
  scheduleFleet();
}

function renderVehicle(vehicle) {
  vehicles.set(vehicle.id, { view: vehicle, receivedAt: performance.now() });
  const main = $("#vehicles");
  let card = main.querySelector(`section.vehicle[data-vehicle="${CSS.escape(vehicle.id)}"]`);
  if (!card) {
    card = $("#vehicle-template").content.firstElementChild.cloneNode(true);
    card.dataset.vehicle = vehicle.id;
    main.appendChild(card);
  }
  $("#no-vehicles").hidden = true;
  $(".vehicle-id", card).textContent = vehicle.id;
  const chip = $(".vehicle-head .chip", card);
  chip.hidden = !vehicle.colour;
  chip.style.backgroundColor = safeColour(vehicle.colour);
  chip.title = vehicle.colour ? `${vehicle.id}'s colour on the fleet map` : "";
  const state = $(".state", card);
  state.textContent = vehicle.state;
  state.dataset.state = vehicle.state;
  $(".reason", card).textContent = vehicle.reason || "";
  const authError = $(".auth-error", card);
  authError.hidden = !vehicle.auth_error;
  authError.textContent = vehicle.auth_error || "";
  const mission = $(".mission", card);
  mission.textContent = vehicle.prompt
    ? `Looking for: ${vehicle.prompt}${vehicle.mission_id ? ` (mission ${vehicle.mission_id})` : ""}`
    : "";
  if (vehicle.prompt_warning) {
    // The prompt's words name something outside the superset the GCS gave.
    const warning = document.createElement("strong");
    warning.className = "prompt-warning";
    warning.textContent = ` Warning: ${vehicle.prompt_warning}`;
    mission.append(warning);
  }
  renderKeyframe(card, vehicle);
  renderProgress(card, vehicle);
  renderMap(card, vehicle);
  renderCandidates(card, vehicle);
  renderFinds(card, vehicle);
  scheduleFleet();
  tick();
}

function renderKeyframe(card, vehicle) {
  const keyframe = vehicle.keyframe;
  const img = $(".keyframe", card);
  const overlay = $(".overlay", card);
  $(".no-keyframe", card).hidden = Boolean(keyframe);
  img.hidden = !keyframe;
  overlay.replaceChildren();
  $(".keyframe-age", card).hidden = !keyframe;
  if (!keyframe) {
    $(".keyframe-info", card).textContent = "";
    return;
  }
  if (card.dataset.keyframe !== keyframe.url) {
    card.dataset.keyframe = keyframe.url;
    loadImage(img, keyframe.url, { replaces: true });
  }
  overlay.setAttribute("viewBox", `0 0 ${keyframe.width} ${keyframe.height}`);
  overlay.setAttribute("font-size", Math.max(12, keyframe.width / 55)); // labels readable at any frame size
  $(".frame", card).style.aspectRatio = `${keyframe.width} / ${keyframe.height}`;
  // A box put to the supervisor carries the candidate's own id (as on the GCS, the card and the finds) and
  // where it stands ("confirmed", "awaiting"); a box put to no one, the verifier's verdict alone.
  const named = [...keyframe.candidates].sort((a, b) => Boolean(a.status) - Boolean(b.status)); // on top
  for (const candidate of named) {
    const [x1, y1, x2, y2] = candidate.box;
    const kind = candidate.status || candidate.verdict;
    svg("rect", { x: x1, y: y1, width: x2 - x1, height: y2 - y1, class: kind }, overlay);
    const label = svg("text", { x: x1, y: Math.max(keyframe.width / 55, y1 - 4), class: kind }, overlay);
    label.textContent = candidate.id ? `${kind} ${candidate.id}` : kind;
  }
  const track = keyframe.track_box;
  if (track) {
    const [x1, y1, x2, y2] = track;
    svg("rect", { x: x1, y: y1, width: x2 - x1, height: y2 - y1, class: "track" }, overlay);
    // Named once: by the answer's box over it when there is one, else here.
    if (!keyframe.candidates.some((c) => keyframe.track_id && c.id === keyframe.track_id)) {
      const label = svg("text", { x: x1, y: Math.min(keyframe.height - 4, y2 + keyframe.width / 50) }, overlay);
      label.textContent = keyframe.track_id
        ? `${keyframe.track_status || "tracked"} ${keyframe.track_id}`
        : "tracked";
    }
  }
  $(".keyframe-info", card).dataset.frame = keyframe.frame_id ?? "";
}

function renderProgress(card, vehicle) {
  const progress = vehicle.progress;
  // Each counter says what it counts: the boxes of every keyframe's answer are detections, not candidates.
  $(".progress", card).textContent = progress
    ? [
        `${plural(progress.keyframes, "keyframe")} checked`,
        ...(progress.detections != null ? [plural(progress.detections, "detection")] : []),
        `${progress.candidates} put to the supervisor`,
        `${progress.rejected} rejected`,
      ].join(" · ")
    : "no search progress reported";
  const search = vehicle.search;
  // No search area, no area figure (a follow has none: "0 % of the area seen" said something false).
  const area = Boolean(search && search.area.length > 2);
  $(".coverage-bar", card).hidden = !area;
  const coverage = area ? search.coverage : null;
  $(".coverage-fill", card).style.width = `${Math.round((coverage || 0) * 100)}%`;
  const pod = vehicle.pod;
  const seen = !area
    ? "no search area"
    : coverage === null
      ? "coverage unknown"
      : `${(coverage * 100).toFixed(0)} % of the area seen`;
  $(".coverage", card).textContent = pod && area
    ? `${seen} · ${(pod.at_target * 100).toFixed(0)} % at POD ≥ ${pod.target_pod} · mean POD ${pod.mean.toFixed(2)}`
    : seen;
  // Keyframes the vehicle kept while the back-end was unreachable, once there were any.
  const kept = vehicle.keyframes;
  const keyframes = $(".keyframes", card);
  keyframes.hidden = !(kept && kept.stored > 0);
  keyframes.textContent = keyframes.hidden
    ? ""
    : `keyframes kept through a back-end outage: ${kept.stored} stored · ${kept.sent} sent · ${kept.dropped} dropped` +
      (kept.waiting ? ` · ${kept.waiting} waiting` : "");
  const item = search && search.mission_item != null
    ? `mission item ${search.mission_item}${search.mission_items != null ? ` of ${search.mission_items}` : ""}`
    : "";
  $(".mission-item", card).textContent = [item, search && search.mode ? `mode ${search.mode}` : ""].filter(Boolean).join(" · ");
  const position = vehicle.position;
  $(".position", card).textContent = position
    ? `vehicle ${position[0].toFixed(6)}, ${position[1].toFixed(6)}` +
      (vehicle.altitude_m != null ? `, ${vehicle.altitude_m.toFixed(0)} m up` : "") +
      (vehicle.heading_deg != null ? `, heading ${vehicle.heading_deg.toFixed(0)}°` : "")
    : "vehicle position unknown";
}

// --- the map: Web Mercator, fitted to what there is to show; tiles only when configured -------------

function mercator(lat, lon) {
  const s = Math.sin((Math.max(-85, Math.min(85, lat)) * Math.PI) / 180);
  return [((lon + 180) / 360) * 256, (0.5 - Math.log((1 + s) / (1 - s)) / (4 * Math.PI)) * 256];
}

function renderMap(card, vehicle) {
  const map = $(".map", card);
  const width = 400;
  const height = 300;
  map.setAttribute("viewBox", `0 0 ${width} ${height}`);
  map.replaceChildren();
  const search = vehicle.search || { area: [], covered: [] };
  const candidates = vehicle.candidates.filter((c) => c.position);
  const points = [
    ...search.area,
    ...search.covered.flat(),
    ...vehicle.track,
    ...(vehicle.position ? [vehicle.position] : []),
    ...candidates.map((c) => [c.position.lat, c.position.lon]),
    ...vehicle.finds.map((f) => [f.position.lat, f.position.lon]),
  ];
  // A find's uncertainty circle is fitted whole, not only its centre.
  const ring = vehicle.finds.filter((f) => f.sigma_m).flatMap((f) => {
    const dLat = f.sigma_m / 111320;
    const dLon = dLat / Math.max(0.01, Math.cos((f.position.lat * Math.PI) / 180));
    return [[f.position.lat - dLat, f.position.lon - dLon], [f.position.lat + dLat, f.position.lon + dLon]];
  });
  if (!points.length) {
    const empty = svg("text", { x: width / 2, y: height / 2, "text-anchor": "middle", class: "empty" }, map);
    empty.textContent = "no positions reported yet";
    $(".map-info", card).textContent = "";
    return;
  }
  const world = [...points, ...ring].map(([lat, lon]) => mercator(lat, lon));
  const xs = world.map((p) => p[0]);
  const ys = world.map((p) => p[1]);
  const [minX, maxX, minY, maxY] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const midLat = points.reduce((sum, p) => sum + p[0], 0) / points.length;
  const metresPerUnit = (40075016.686 * Math.cos((midLat * Math.PI) / 180)) / 256;
  const least = 60 / metresPerUnit; // at least 60 m across
  // Fitted inside a margin the marks drawn above and beside a point need (a find's pin is 24 px tall).
  const margin = 30;
  const scale = Math.min(
    (width - 2 * margin) / Math.max(maxX - minX, least),
    (height - 2 * margin) / Math.max(maxY - minY, least),
  ); // pixels per world unit
  const cx = (minX + maxX) / 2;
  const cy = (minY + maxY) / 2;
  const project = ([lat, lon]) => {
    const [x, y] = mercator(lat, lon);
    return [width / 2 + (x - cx) * scale, height / 2 + (y - cy) * scale];
  };
  if (mapTiles) drawTiles(map, scale, cx, cy, width, height);
  const path = (ring) => ring.map(project).map(([x, y], i) => `${i ? "L" : "M"}${x.toFixed(1)},${y.toFixed(1)}`).join(" ");
  const pod = vehicle.pod;
  // One of several vehicles of a mission: its own covered area and POD cells are on the mission's merged
  // map (not sent twice), drawn here under its part; its POD figures and legend are its own.
  const mission = vehicle.on_mission_map ? missions.find((m) => m.mission_id === vehicle.mission_id) : null;
  const cells = mission ? mission.pod : pod;
  if (cells && cells.values) drawPod(map, cells, path);
  renderLegend(card, pod);
  // With a POD map the footprints are an outline: what the camera pointed at is not what was searched.
  const covered = cells ? "covered outline" : "covered";
  const rings = mission ? mission.covered : search.covered;
  for (const ring of rings) if (ring.length > 2) svg("path", { d: `${path(ring)} Z`, class: covered }, map);
  if (search.area.length > 2) svg("path", { d: `${path(search.area)} Z`, class: "area" }, map);
  if (vehicle.track.length > 1) svg("path", { d: path(vehicle.track), class: "track" }, map);
  for (const candidate of candidates) {
    const [x, y] = project([candidate.position.lat, candidate.position.lon]);
    svg("circle", { cx: x, cy: y, r: 6, class: "candidate-mark" }, map);
    const label = svg("text", { x: x + 8, y: y - 6 }, map);
    label.textContent = `candidate ${candidate.status}`;
  }
  for (const find of vehicle.finds) {
    const [x, y] = project([find.position.lat, find.position.lon]);
    if (find.sigma_m) svg("circle", { cx: x, cy: y, r: Math.max(4, (find.sigma_m / metresPerUnit) * scale), class: "sigma" }, map);
    svg("path", { d: `M${x},${y} l-7,-16 a7.5,7.5 0 1 1 14,0 z`, class: "find-mark" }, map);
    const label = svg("text", { x: x + 9, y: y - 12 }, map);
    label.textContent = `find ${formatTime(find.time).slice(11, 16)}`;
  }
  if (vehicle.position) {
    const [x, y] = project(vehicle.position);
    const heading = vehicle.heading_deg ?? 0;
    svg("path", { d: "M0,-10 L6,7 L0,3 L-6,7 Z", transform: `translate(${x},${y}) rotate(${heading})`, class: "vehicle-mark" }, map);
  }
  drawScale(map, metresPerUnit / scale, height);
  const earlier = vehicle.earlier_areas || 0;
  $(".map-info", card).textContent =
    (mapTiles ? "map tiles from the configured tile server" : "drawn from the reported positions (no map tiles)") +
    (earlier ? ` · ${earlier} earlier search area${earlier > 1 ? "s" : ""} of this mission in the downloads` : "");
}

// The POD grid: north-up cells from its south-west corner, one byte a cell (0-250 POD, 255 outside the
// area). A row's neighbouring cells of one band are drawn as one shape; a place at POD 0 is left blank.
function bandOf(pod, value) {
  if (value === 0 || value > 250) return -1;
  const p = value / 250;
  const last = pod.bands.length - 1;
  return pod.bands.findIndex((b, i) => p >= b.low && (p < b.high || (i === last && p <= b.high)));
}

function drawPod(map, pod, path) {
  let cells;
  try {
    cells = Uint8Array.from(atob(pod.values), (c) => c.charCodeAt(0));
  } catch {
    return;
  }
  if (cells.length !== pod.rows * pod.cols) return;
  const [lat0, lon0] = pod.origin;
  const [dLat, dLon] = pod.cell_deg;
  const layer = svg("g", { class: "pod" }, map);
  for (let r = 0; r < pod.rows; r++) {
    let c = 0;
    while (c < pod.cols) {
      const band = bandOf(pod, cells[r * pod.cols + c]);
      let end = c + 1;
      while (end < pod.cols && bandOf(pod, cells[r * pod.cols + end]) === band) end++;
      if (band >= 0) {
        const south = lat0 + r * dLat;
        const north = south + dLat;
        const west = lon0 + c * dLon;
        const east = lon0 + end * dLon;
        const shape = svg("path", { d: `${path([[south, west], [south, east], [north, east], [north, west]])} Z`, class: "pod-cell" }, layer);
        shape.setAttribute("fill", pod.bands[band].colour);
        shape.dataset.pod = pod.bands[band].low;
      }
      c = end;
    }
  }
}

function renderLegend(card, pod) {
  const legend = $(".pod-legend", card);
  legend.hidden = !pod;
  if (!pod) return;
  const list = $(".pod-bands", legend);
  list.replaceChildren();
  for (const band of pod.bands) {
    const item = document.createElement("li");
    const swatch = document.createElement("span");
    swatch.className = "pod-swatch";
    swatch.style.backgroundColor = band.colour;
    item.append(swatch, `${Math.round(band.low * 100)}-${Math.round(band.high * 100)} %`);
    list.appendChild(item);
  }
  $(".pod-meaning", legend).textContent = `${pod.meaning}. Target: ${pod.target_pod} for a ${pod.posture} ${pod.target}, from ${pod.looks} analysed keyframes.`;
}

function drawTiles(map, scale, cx, cy, width, height) {
  const zoom = Math.max(0, Math.min(20, Math.floor(Math.log2(scale))));
  const tileWorld = 256 / 2 ** zoom; // one tile in world units
  const size = tileWorld * scale;
  const left = cx - width / 2 / scale;
  const top = cy - height / 2 / scale;
  const layer = svg("g", { class: "tiles" }, map);
  for (let tx = Math.floor(left / tileWorld); tx * tileWorld < left + width / scale; tx++) {
    for (let ty = Math.floor(top / tileWorld); ty * tileWorld < top + height / scale; ty++) {
      if (ty < 0 || ty >= 2 ** zoom) continue;
      const wrapped = ((tx % 2 ** zoom) + 2 ** zoom) % 2 ** zoom;
      const href = mapTiles.replace("{z}", zoom).replace("{x}", wrapped).replace("{y}", ty);
      svg("image", {
        href,
        x: (tx * tileWorld - left) * scale,
        y: (ty * tileWorld - top) * scale,
        width: size + 0.5,
        height: size + 0.5,
        preserveAspectRatio: "none",
      }, layer);
    }
  }
}

function drawScale(map, metresPerPixel, height) {
  const target = metresPerPixel * 100;
  const nice = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000].find((m) => m >= target / 2) || 10000;
  const pixels = nice / metresPerPixel;
  const group = svg("g", { class: "scale", transform: `translate(10,${height - 12})` }, map);
  svg("line", { x1: 0, y1: 0, x2: pixels, y2: 0 }, group);
  svg("line", { x1: 0, y1: -4, x2: 0, y2: 4 }, group);
  svg("line", { x1: pixels, y1: -4, x2: pixels, y2: 4 }, group);
  const label = svg("text", { x: pixels + 5, y: 4 }, group);
  label.textContent = nice >= 1000 ? `${nice / 1000} km` : `${nice} m`;
}

// --- candidates and finds ----------------------------------------------------------------------------

function renderCandidates(card, vehicle) {
  const box = $(".candidates", card);
  const seen = new Set();
  for (const candidate of vehicle.candidates) {
    seen.add(candidate.id);
    let item = box.querySelector(`article[data-candidate="${CSS.escape(candidate.id)}"]`);
    if (!item) {
      item = $("#candidate-template").content.firstElementChild.cloneNode(true);
      item.dataset.candidate = candidate.id;
      $(".confirm", item).addEventListener("click", () => decide(vehicle.id, candidate.id, "confirm", item));
      $(".reject", item).addEventListener("click", () => decide(vehicle.id, candidate.id, "reject", item));
      box.appendChild(item);
    }
    $(".candidate-id", item).textContent = `candidate ${candidate.id}`;
    const verdict = $(".verdict", item);
    verdict.textContent = candidate.verdict;
    verdict.dataset.verdict = candidate.verdict;
    // The supervisor's standing decision, and apart from it what the vehicle reports its GCS decided (its
    // word only: it leaves the decision open here).
    const status = candidate.decided_by ? `${candidate.status} by ${candidate.decided_by}` : candidate.status;
    $(".status", item).textContent = candidate.reported ? `${status} (the vehicle's report: ${candidate.reported})` : status;
    item.dataset.status = candidate.status;
    $(".justification", item).textContent = candidate.justification || "(no justification)";
    const alike = candidate.alike || 0;
    $(".alike", item).hidden = alike === 0;
    $(".alike", item).textContent = alike === 1
      ? "1 other candidate in that view fits what was checked as well: this one was chosen by the detector's score alone."
      : `${alike} other candidates in that view fit what was checked as well: this one was chosen by the detector's score alone.`;
    const unjudged = candidate.unjudged || [];
    $(".unjudged", item).hidden = unjudged.length === 0;
    $(".unjudged-words", item).textContent = unjudged.join("; ");
    $(".position", item).textContent = formatPosition(candidate.position);
    const open = candidate.status === "awaiting";
    for (const button of item.querySelectorAll(".decide button")) button.disabled = !open || item.dataset.sent === "1";
    if (!open) $(".decision", item).textContent = candidate.status;
    showCrop(item, candidate.crop_url, candidate.crop_box, `candidate ${candidate.id}`);
  }
  for (const item of box.querySelectorAll("article.candidate")) {
    if (!seen.has(item.dataset.candidate)) item.remove();
  }
  // The vehicle shows one undecided candidate at a time: say how many wait behind it, and which were
  // dropped undecided because more waited than it keeps.
  const more = vehicle.awaiting_more || [];
  const queue = $(".queue", card);
  queue.hidden = more.length === 0;
  queue.textContent = more.length
    ? `${more.length} more awaiting a decision, each shown once the one above is decided: ${more.join(", ")}`
    : "";
  const dropped = vehicle.dropped_undecided || [];
  const gone = $(".dropped", card);
  gone.hidden = dropped.length === 0;
  gone.textContent = dropped.length
    ? `Dropped undecided (too many awaited a decision): ${dropped.join(", ")}. Not rejected: the search proposes them again if it sees them again.`
    : "";
}

function renderFinds(card, vehicle) {
  const list = $(".finds", card);
  $(".no-finds", card).hidden = vehicle.finds.length > 0;
  const seen = new Set();
  for (const find of vehicle.finds) {
    const key = `${find.mission_id}/${find.candidate_id}`;
    seen.add(key);
    let item = list.querySelector(`li[data-find="${CSS.escape(key)}"]`);
    if (!item) {
      item = $("#find-template").content.firstElementChild.cloneNode(true);
      item.dataset.find = key;
      list.appendChild(item);
    }
    $(".where", item).textContent = formatPosition(find.position, find.sigma_m);
    $(".when", item).textContent = formatTime(find.time);
    $(".seen", item).textContent = find.seen; // how old the position is, worded as on the TAK map
    $(".who", item).textContent = `confirmed by ${find.decided_by || find.confirmed_by}`;
    $(".what", item).textContent = `${find.prompt} (mission ${find.mission_id})`;
    $(".find-id", item).textContent = `candidate ${find.candidate_id}`;
    showCrop(item, find.crop_url, find.crop_box, `find ${find.candidate_id}`);
  }
  for (const item of list.querySelectorAll("li.find")) {
    if (!seen.has(item.dataset.find)) item.remove();
  }
  const downloads = $(".downloads", card);
  // The mission under way too (its track, areas and POD map for the ground teams), before any find.
  const flying = vehicle.mission_id && (vehicle.search || vehicle.track.length) ? [vehicle.mission_id] : [];
  const missions = [...new Set([...vehicle.finds.map((f) => f.mission_id), ...flying])];
  if (downloads.dataset.missions !== missions.join(",")) {
    downloads.dataset.missions = missions.join(",");
    downloads.replaceChildren();
    for (const mission of missions) {
      for (const kind of ["geojson", "kml"]) {
        const button = document.createElement("button");
        button.type = "button";
        button.textContent = `${kind.toUpperCase()}${missions.length > 1 ? ` ${mission}` : ""}`;
        button.addEventListener("click", () => download(vehicle.id, mission, kind, card));
        downloads.appendChild(button);
      }
    }
  }
}

// The vehicle's crop is cut from the camera's native frame around the candidate with the verifier's
// margin; a person 12 px tall in the keyframe is a few dozen pixels in it. The card zooms on the box so
// the person stands 1/1.4 of the card's height (171 px in the 15rem card), the box drawn; a click shows
// the whole crop, larger, in the dialog.
const BOX_SHARE = 1 / 1.4;

function showCrop(item, url, cropBox, caption = "") {
  const img = $(".crop", item);
  const overlay = $(".crop-overlay", item);
  const frame = $(".crop-box", item);
  img.hidden = !url;
  overlay.hidden = !url;
  $(".no-crop", item).hidden = Boolean(url);
  frame.dataset.zoomable = url ? "1" : "";
  frame.onclick = url ? () => showLargeCrop(img, cropBox, caption) : null;
  frame.onkeydown = url ? (event) => {
    if (event.key === "Enter" || event.key === " ") {
      event.preventDefault();
      showLargeCrop(img, cropBox, caption);
    }
  } : null;
  if (!url) return;
  const draw = () => {
    const inner = drawCropBox(img, overlay, cropBox);
    if (inner !== undefined) zoomOnBox($(".crop-view", item), frame, img, inner);
  };
  img.onload = draw;
  if (img.dataset.url !== url) {
    img.dataset.url = url;
    loadImage(img, url);
  } else {
    draw();
  }
}

// The box inside the crop, clamped to it (null when there is none worth drawing); undefined before the
// picture has loaded.
function drawCropBox(img, overlay, cropBox) {
  overlay.replaceChildren();
  const width = img.naturalWidth;
  const height = img.naturalHeight;
  if (!width) return undefined;
  overlay.setAttribute("viewBox", `0 0 ${width} ${height}`);
  if (!Array.isArray(cropBox) || cropBox.length !== 4) return null;
  const clamp = (v, hi) => Math.min(hi, Math.max(0, Number(v) || 0));
  const [x1, y1, x2, y2] = [clamp(cropBox[0], width), clamp(cropBox[1], height), clamp(cropBox[2], width), clamp(cropBox[3], height)];
  if (x2 - x1 < 1 || y2 - y1 < 1) return null;
  svg("rect", { x: x1, y: y1, width: x2 - x1, height: y2 - y1 }, overlay);
  return [x1, y1, x2, y2];
}

// Scale and place the crop in its frame so the box fills BOX_SHARE of it, centred where the crop allows
// (never smaller than the whole crop fitted).
function zoomOnBox(view, frame, img, inner) {
  const room = [frame.clientWidth, frame.clientHeight];
  if (!room[0] || !room[1]) return; // not laid out yet: the next render places it
  const size = [img.naturalWidth, img.naturalHeight];
  let scale = Math.min(room[0] / size[0], room[1] / size[1]);
  if (inner) {
    const boxScale = Math.min((room[0] * BOX_SHARE) / (inner[2] - inner[0]), (room[1] * BOX_SHARE) / (inner[3] - inner[1]));
    scale = Math.max(scale, boxScale);
  }
  const centre = inner ? [(inner[0] + inner[2]) / 2, (inner[1] + inner[3]) / 2] : [size[0] / 2, size[1] / 2];
  const place = (i) => {
    const shown = size[i] * scale;
    if (shown <= room[i]) return (room[i] - shown) / 2;
    return Math.min(0, Math.max(room[i] - shown, room[i] / 2 - centre[i] * scale));
  };
  view.style.width = `${size[0] * scale}px`;
  view.style.height = `${size[1] * scale}px`;
  view.style.left = `${place(0)}px`;
  view.style.top = `${place(1)}px`;
}

// The whole crop in the dialog, as large as the window allows, its box drawn.
function showLargeCrop(source, cropBox, caption) {
  if (!source.naturalWidth) return;
  const dialog = $("#crop-dialog");
  const img = $(".crop", dialog);
  const overlay = $(".crop-overlay", dialog);
  img.src = source.src;
  drawCropBox(source, overlay, cropBox);
  const scale = Math.min((window.innerWidth * 0.9) / source.naturalWidth, (window.innerHeight * 0.8) / source.naturalHeight);
  const view = $(".crop-large", dialog);
  view.style.width = `${Math.round(source.naturalWidth * scale)}px`;
  view.style.height = `${Math.round(source.naturalHeight * scale)}px`;
  const size = `${source.naturalWidth}x${source.naturalHeight} px from the camera's frame`;
  $(".crop-caption", dialog).textContent = caption ? `${caption}: ${size}` : size;
  if (!dialog.open) dialog.showModal();
}

async function loadImage(img, url, { replaces = false } = {}) {
  if (images.has(url)) {
    if (images.get(url)) img.src = images.get(url);
    return;
  }
  images.set(url, ""); // one fetch per image
  const response = await fetch(url, { headers: authHeaders() });
  if (!response.ok) {
    images.delete(url);
    return;
  }
  const objectUrl = URL.createObjectURL(await response.blob());
  if (replaces) {
    // A keyframe replaces the one before it: free the old picture.
    const old = img.src;
    if (old.startsWith("blob:")) {
      for (const [key, value] of images) if (value === old) images.delete(key);
      URL.revokeObjectURL(old);
    }
  }
  images.set(url, objectUrl);
  if (img.dataset.url === url || replaces) img.src = objectUrl;
}

async function download(vehicleId, missionId, kind, card) {
  // A download that fails says so under the buttons (it used to do nothing at all).
  let note = $(".download-error", card);
  if (!note) {
    note = document.createElement("p");
    note.className = "download-error error";
    note.setAttribute("role", "alert");
    $(".downloads", card).closest("h3").after(note);
  }
  note.hidden = true;
  const failed = (why) => {
    note.textContent = `${kind.toUpperCase()} of mission ${missionId} not downloaded: ${why}`;
    note.hidden = false;
  };
  const url = `/v1/missions/${encodeURIComponent(missionId)}/finds.${kind}?vehicle_id=${encodeURIComponent(vehicleId)}`;
  let response;
  try {
    response = await fetch(url, { headers: authHeaders() });
  } catch {
    failed("the back-end did not answer");
    return;
  }
  if (!response.ok) {
    const detail = await response.json().then((body) => body.detail).catch(() => "");
    failed(`the back-end answered ${response.status}${typeof detail === "string" && detail ? ` (${detail})` : ""}`);
    return;
  }
  const link = document.createElement("a");
  link.href = URL.createObjectURL(await response.blob());
  link.download = `cloudtrack-${vehicleId}-${missionId}-finds.${kind}`;
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 10_000);
}

// --- the fleet: one map per mission, its legend, one queue of every vehicle's candidates ---------------

const SILENT_S = 10; // a vehicle with no report for longer is marked silent in the legend
const STATE_WORDS = {
  IDLE: "idle",
  SEARCHING: "searching",
  ACQUIRING: "tracking",
  FOLLOWING: "tracking",
  AWAITING_SUPERVISOR: "awaiting supervisor",
  CONFIRMED: "confirmed find",
  REJECTED: "rejected, searching on",
  LOST: "lost the target",
  ABORTED: "left the search (aborted)",
  UNKNOWN: "credentials refused",
};

// Colours come from the back-end's palette; anything else is drawn grey, never inserted as markup.
function safeColour(colour) {
  return /^#[0-9a-fA-F]{6}$/.test(colour || "") ? colour : "#5d6670";
}

// The back-end says when a vehicle has left its mission's search (backend.fleet_dropout: RTL / LAND, an
// abort, silent too long) and why.
function stateWords(vehicle) {
  if (vehicle.left) return `left the search (${vehicle.left})`;
  return STATE_WORDS[vehicle.state] || vehicle.state.toLowerCase();
}

function formatArea(m2) {
  return m2 >= 10000 ? `${(m2 / 10000).toFixed(1)} ha` : `${Math.round(m2)} m²`;
}

function scheduleFleet() {
  // A fleet's vehicles report many times a second: the fleet is drawn at most every 200 ms.
  if (fleetTimer === null) {
    fleetTimer = setTimeout(() => {
      fleetTimer = null;
      renderFleet();
    }, 200);
  }
}

function renderFleet() {
  const views = [...vehicles.values()].map((known) => known.view);
  const box = $("#fleet-maps");
  const ids = new Set(missions.map((m) => m.mission_id));
  for (const figure of box.querySelectorAll("figure.mission-map")) {
    if (!ids.has(figure.dataset.mission)) figure.remove();
  }
  for (const mission of missions) {
    let figure = box.querySelector(`figure.mission-map[data-mission="${CSS.escape(mission.mission_id)}"]`);
    if (!figure) {
      figure = $("#mission-template").content.firstElementChild.cloneNode(true);
      figure.dataset.mission = mission.mission_id;
      box.appendChild(figure);
    }
    const members = views.filter((v) => v.mission_id === mission.mission_id).sort((a, b) => (a.id < b.id ? -1 : 1));
    const coverage = mission.coverage == null ? "" : ` · ${(mission.coverage * 100).toFixed(0)} % of the area covered`;
    $(".mission-title", figure).textContent = `Mission ${mission.mission_id}: ${plural(members.length, "vehicle")}${coverage}`;
    drawFleetMap(figure, mission, members);
    renderFleetLegend(figure, members);
  }
  const queued = renderQueue(views);
  $("#fleet").hidden = missions.length === 0 && queued === 0;
  tick();
}

function drawFleetMap(figure, mission, members) {
  const map = $(".fleet-map", figure);
  const width = 800;
  const height = 500;
  map.setAttribute("viewBox", `0 0 ${width} ${height}`);
  map.replaceChildren();
  const parts = (v) => (v.search && v.search.area.length > 2 ? v.search.area : []);
  const candidates = members.flatMap((v) => v.candidates.filter((c) => c.position).map((c) => [v, c]));
  const unflown = mission.unflown || [];
  const points = [
    ...mission.area.flat(),
    ...unflown.flatMap((u) => u.rings.flat()),
    ...members.flatMap((v) => [...parts(v), ...v.track, ...(v.position ? [v.position] : [])]),
    ...candidates.map(([, c]) => [c.position.lat, c.position.lon]),
    ...members.flatMap((v) => v.finds.map((f) => [f.position.lat, f.position.lon])),
  ];
  if (!points.length) {
    const empty = svg("text", { x: width / 2, y: height / 2, "text-anchor": "middle", class: "empty" }, map);
    empty.textContent = "no positions or parts reported yet";
    $(".fleet-info", figure).textContent = "";
    renderLegend(figure, null);
    return;
  }
  const world = points.map(([lat, lon]) => mercator(lat, lon));
  const xs = world.map((p) => p[0]);
  const ys = world.map((p) => p[1]);
  const [minX, maxX, minY, maxY] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const midLat = points.reduce((sum, p) => sum + p[0], 0) / points.length;
  const metresPerUnit = (40075016.686 * Math.cos((midLat * Math.PI) / 180)) / 256;
  const least = 60 / metresPerUnit;
  const margin = 36;
  const scale = Math.min(
    (width - 2 * margin) / Math.max(maxX - minX, least),
    (height - 2 * margin) / Math.max(maxY - minY, least),
  );
  const cx = (minX + maxX) / 2;
  const cy = (minY + maxY) / 2;
  const project = ([lat, lon]) => {
    const [x, y] = mercator(lat, lon);
    return [width / 2 + (x - cx) * scale, height / 2 + (y - cy) * scale];
  };
  const path = (ring) => ring.map(project).map(([x, y], i) => `${i ? "L" : "M"}${x.toFixed(1)},${y.toFixed(1)}`).join(" ");
  const titled = (node, text) => {
    svg("title", {}, node).textContent = text;
    return node;
  };
  if (mapTiles) drawTiles(map, scale, cx, cy, width, height);
  // The mission's merged map under the vehicles: its POD map where there is one, else its covered area.
  if (mission.pod) drawPod(map, mission.pod, path);
  else for (const ring of mission.covered) if (ring.length > 2) svg("path", { d: `${path(ring)} Z`, class: "merged-covered" }, map);
  renderLegend(figure, mission.pod);
  for (const ring of mission.area) if (ring.length > 2) svg("path", { d: `${path(ring)} Z`, class: "merged-area" }, map);
  // What a vehicle that left the search leaves unflown: for the re-plan, in its colour, named.
  const colourOf = new Map(members.map((v) => [v.id, safeColour(v.colour)]));
  for (const left of unflown) {
    const d = left.rings.filter((ring) => ring.length > 2).map((ring) => `${path(ring)} Z`).join(" ");
    if (!d) continue;
    const colour = colourOf.get(left.vehicle_id) || safeColour("");
    const shape = svg("path", { d, class: "unflown", stroke: colour, fill: colour, "fill-rule": "evenodd" }, map);
    shape.dataset.vehicle = left.vehicle_id;
    titled(shape, `${left.vehicle_id} left ${formatArea(left.area_m2)} of its part unflown`);
  }
  // Each vehicle in its colour, and named: its part, its track, where it is and what it does.
  for (const vehicle of members) {
    const colour = safeColour(vehicle.colour);
    const area = parts(vehicle);
    if (area.length) {
      const part = svg("path", { d: `${path(area)} Z`, class: "part", stroke: colour, fill: colour }, map);
      part.dataset.vehicle = vehicle.id;
      titled(part, `${vehicle.id}'s part of the area`);
      const [sx, sy] = area.map(project).reduce(([ax, ay], [x, y]) => [ax + x, ay + y], [0, 0]);
      const label = svg("text", { x: sx / area.length, y: sy / area.length, "text-anchor": "middle", class: "part-label", fill: colour }, map);
      label.dataset.vehicle = vehicle.id;
      label.textContent = `${vehicle.id} part`;
    }
    if (vehicle.track.length > 1) {
      const track = svg("path", { d: path(vehicle.track), class: "fleet-track", stroke: colour }, map);
      track.dataset.vehicle = vehicle.id;
      titled(track, `${vehicle.id}'s track`);
    }
    const at = vehicle.position || vehicle.track[vehicle.track.length - 1];
    if (at) {
      const [x, y] = project(at);
      if (vehicle.position) {
        const mark = svg("path", {
          d: "M0,-11 L7,8 L0,4 L-7,8 Z",
          transform: `translate(${x},${y}) rotate(${vehicle.heading_deg ?? 0})`,
          class: "fleet-vehicle",
          fill: colour,
        }, map);
        mark.dataset.vehicle = vehicle.id;
        titled(mark, `${vehicle.id}: ${stateWords(vehicle)}`);
      }
      const label = svg("text", { x: x + 10, y: y - 8, class: "vehicle-label" }, map);
      label.dataset.vehicle = vehicle.id;
      label.textContent = `${vehicle.id} · ${stateWords(vehicle)}`;
    }
    for (const find of vehicle.finds) {
      const [x, y] = project([find.position.lat, find.position.lon]);
      svg("path", { d: `M${x},${y} l-7,-16 a7.5,7.5 0 1 1 14,0 z`, class: "find-mark" }, map);
      const label = svg("text", { x: x + 9, y: y - 12 }, map);
      label.textContent = `find of ${vehicle.id}`;
    }
  }
  for (const [vehicle, candidate] of candidates) {
    const [x, y] = project([candidate.position.lat, candidate.position.lon]);
    const mark = svg("circle", { cx: x, cy: y, r: 6, class: "fleet-candidate", stroke: safeColour(vehicle.colour) }, map);
    mark.dataset.vehicle = vehicle.id;
    const label = svg("text", { x: x + 8, y: y + 14 }, map);
    label.textContent = `candidate of ${vehicle.id}`;
  }
  drawScale(map, metresPerUnit / scale, height);
  $(".fleet-info", figure).textContent =
    (mapTiles ? "map tiles from the configured tile server" : "drawn from the reported positions (no map tiles)") +
    (mission.pod ? " · the mission's POD map, every vehicle's looks merged" : " · green: covered by any vehicle");
}

function renderFleetLegend(figure, members) {
  const list = $(".fleet-legend", figure);
  list.replaceChildren();
  for (const vehicle of members) {
    const item = document.createElement("li");
    item.dataset.vehicle = vehicle.id;
    const chip = document.createElement("span");
    chip.className = "chip";
    chip.style.backgroundColor = safeColour(vehicle.colour);
    const id = document.createElement("span");
    id.className = "legend-id";
    id.textContent = vehicle.id;
    const state = document.createElement("span");
    state.className = "legend-state";
    state.textContent = stateWords(vehicle);
    const coverage = document.createElement("span");
    coverage.className = "legend-coverage muted";
    const search = vehicle.search;
    coverage.textContent = search && search.area.length > 2
      ? `${(search.coverage * 100).toFixed(0)} % of its part covered`
      : "no part of the area";
    const unflown = (missions.find((m) => m.mission_id === vehicle.mission_id)?.unflown || []).find((u) => u.vehicle_id === vehicle.id);
    if (unflown) coverage.textContent += ` · ${formatArea(unflown.area_m2)} unflown`;
    const age = document.createElement("span");
    age.className = "legend-age muted";
    item.append(chip, id, state, coverage, age);
    item.title = `show ${vehicle.id}'s console`;
    item.addEventListener("click", () => {
      document.querySelector(`section.vehicle[data-vehicle="${CSS.escape(vehicle.id)}"]`)?.scrollIntoView({ behavior: "smooth" });
    });
    list.appendChild(item);
  }
}

// Every vehicle's candidate awaiting the supervisor in one list, newest first (the one that began waiting
// last on top), each naming the vehicle that sees it by id and colour. The number of entries.
function renderQueue(views) {
  const now = performance.now();
  const entries = [];
  for (const vehicle of views) {
    const known = vehicles.get(vehicle.id);
    const extra = known ? (now - known.receivedAt) / 1000 : 0;
    for (const candidate of vehicle.candidates) entries.push({ vehicle, candidate, age: candidate.age_s + extra });
  }
  entries.sort((a, b) => a.age - b.age || (a.vehicle.id < b.vehicle.id ? -1 : 1));
  const list = $("#queue");
  const keep = new Set();
  for (const { vehicle, candidate } of entries) {
    const key = `${vehicle.id}/${candidate.id}`;
    keep.add(key);
    let item = list.querySelector(`li.queued[data-key="${CSS.escape(key)}"]`);
    if (!item) {
      item = $("#queued-template").content.firstElementChild.cloneNode(true);
      item.dataset.key = key;
      item.dataset.vehicle = vehicle.id;
      item.dataset.candidate = candidate.id;
      $(".confirm", item).addEventListener("click", () => decide(vehicle.id, candidate.id, "confirm", item));
      $(".reject", item).addEventListener("click", () => decide(vehicle.id, candidate.id, "reject", item));
    }
    list.appendChild(item); // in the queue's order
    const colour = safeColour(vehicle.colour);
    item.style.borderLeftColor = colour;
    $(".chip", item).style.backgroundColor = colour;
    $(".queued-vehicle", item).textContent = vehicle.id;
    $(".candidate-id", item).textContent = `candidate ${candidate.id}`;
    const verdict = $(".verdict", item);
    verdict.textContent = candidate.verdict;
    verdict.dataset.verdict = candidate.verdict;
    $(".status", item).textContent = candidate.decided_by ? `${candidate.status} by ${candidate.decided_by}` : candidate.status;
    item.dataset.status = candidate.status;
    $(".justification", item).textContent = candidate.justification || "(no justification)";
    $(".position", item).textContent = formatPosition(candidate.position);
    const more = vehicle.awaiting_more || [];
    $(".more", item).hidden = more.length === 0;
    $(".more", item).textContent = more.length ? `${more.length} more of ${vehicle.id} wait behind it` : "";
    const open = candidate.status === "awaiting";
    for (const button of item.querySelectorAll(".decide button")) button.disabled = !open || item.dataset.sent === "1";
    if (!open) $(".decision", item).textContent = candidate.status;
    showCrop(item, candidate.crop_url, candidate.crop_box, `candidate ${candidate.id} of ${vehicle.id}`);
  }
  for (const item of list.querySelectorAll("li.queued")) if (!keep.has(item.dataset.key)) item.remove();
  $("#queue-empty").hidden = entries.length > 0;
  $("#queue-count").textContent = entries.length ? `(${entries.length})` : "";
  return entries.length;
}

function tick() {
  const now = performance.now();
  for (const [id, { view, receivedAt }] of vehicles) {
    const card = document.querySelector(`section.vehicle[data-vehicle="${CSS.escape(id)}"]`);
    if (!card) continue;
    const extra = (now - receivedAt) / 1000;
    $(".seen", card).textContent = view.auth_error && !view.mission_id && view.state === "UNKNOWN"
      ? "no report accepted"
      : `last report ${formatAge(view.age_s + extra)}`;
    if (view.keyframe) {
      // The live view is the newest keyframe the vehicle sent for analysis, not a video: its age is on it,
      // marked once older than LIVE_S (docs/backend.md, "The live view's age").
      const age = view.keyframe.age_s + extra;
      $(".keyframe-info", card).textContent = `keyframe ${view.keyframe.frame_id ?? ""} · received ${formatAge(age)}`;
      const badge = $(".keyframe-age", card);
      badge.textContent = age > LIVE_S ? `not live: ${Math.round(age)} s old` : `${Math.round(age)} s old`;
      badge.dataset.stale = age > LIVE_S ? "1" : "";
    }
    for (const candidate of view.candidates) {
      const item = card.querySelector(`article[data-candidate="${CSS.escape(candidate.id)}"]`);
      if (item) $(".age", item).textContent = `seen ${formatAge(candidate.age_s + extra)}`;
      const queued = document.querySelector(`li.queued[data-key="${CSS.escape(`${id}/${candidate.id}`)}"]`);
      if (queued) $(".age", queued).textContent = `put to the supervisor ${formatAge(candidate.age_s + extra)}`;
    }
    for (const item of document.querySelectorAll(`.fleet-legend li[data-vehicle="${CSS.escape(id)}"]`)) {
      const age = view.age_s + extra;
      $(".legend-age", item).textContent = age > SILENT_S ? `silent, last report ${formatAge(age)}` : "";
    }
  }
}

async function decide(vehicleId, candidateId, decision, item) {
  for (const button of item.querySelectorAll(".decide button")) button.disabled = true;
  item.dataset.sent = "1";
  const note = $(".decision", item);
  note.textContent = `${decision} sent…`;
  // The API's one decision endpoint; require_awaiting: 409 instead of deciding on a candidate gone stale,
  // and 409 naming the decision that stands when someone decided first.
  const url = `/v1/vehicles/${encodeURIComponent(vehicleId)}/decisions?require_awaiting=true`;
  const response = await fetch(url, {
    method: "POST",
    headers: authHeaders({ "Content-Type": "application/json" }),
    body: JSON.stringify({ candidate_id: candidateId, action: decision, operator: "supervisor page", via: "supervisor page" }),
  });
  if (response.ok) {
    note.textContent = `${decision} sent, waiting for the vehicle`;
    return;
  }
  item.dataset.sent = "";
  const detail = await response.json().catch(() => ({}));
  note.textContent = `not sent: ${detail.detail || response.status}`;
  for (const button of item.querySelectorAll(".decide button")) button.disabled = response.status === 409;
}

$("#login").addEventListener("submit", login);
$("#logout").addEventListener("click", () => showLogin());
setInterval(tick, 1000);

async function start() {
  // With no supervisor token configured the back-end refuses every token: say so, ask for none.
  const answer = await fetch("/supervisor/api/enabled").then((r) => r.json()).catch(() => ({ enabled: true }));
  if (!answer.enabled) {
    $("#disabled").hidden = false;
    $("#login").hidden = true;
    $("#no-vehicles").hidden = true;
    setConnection("off");
    return;
  }
  if (token) {
    $("#logout").hidden = false;
    connect();
  } else {
    showLogin();
  }
}

start();
