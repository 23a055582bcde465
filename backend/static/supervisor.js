// CloudTrack supervisor page: live vehicle states and candidates, Confirm / Reject.
// The token is a bearer token like the API's; it lives in this tab's sessionStorage only. Live updates are
// Server-Sent Events read with fetch() so the token travels in a header, never in a URL (or a proxy log).
// Everything that came from a vehicle or a VLM is inserted as text, never as HTML.
"use strict";

const TOKEN_KEY = "cloudtrack.supervisor_token";
const $ = (selector, root = document) => root.querySelector(selector);
let token = sessionStorage.getItem(TOKEN_KEY) || "";
let snapshot = { vehicles: [] };
let receivedAt = performance.now();
let stream = null;
const cropUrls = new Map(); // crop URL -> object URL of the fetched image

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
  render(await response.json());
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
    // The server ends every stream after a while (see supervisor_routes): open the next one at once.
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
  if (kind === "state" && data.length) render(JSON.parse(data.join("\n")));
}

// --- rendering ------------------------------------------------------------------------------------

function formatAge(seconds) {
  if (seconds < 60) return `${Math.round(seconds)} s ago`;
  if (seconds < 3600) return `${Math.floor(seconds / 60)} min ${Math.round(seconds % 60)} s ago`;
  return `${(seconds / 3600).toFixed(1)} h ago`;
}

function formatPosition(position) {
  if (!position) return "position unknown";
  const text = `${position.lat.toFixed(6)}, ${position.lon.toFixed(6)}`;
  return position.uncertainty_m != null ? `${text} (± ${Math.round(position.uncertainty_m)} m)` : text;
}

function elapsed() {
  return (performance.now() - receivedAt) / 1000;
}

function render(data) {
  snapshot = data;
  receivedAt = performance.now();
  const main = $("#vehicles");
  const seen = new Set();
  for (const vehicle of data.vehicles) {
    seen.add(vehicle.id);
    let card = main.querySelector(`section.vehicle[data-vehicle="${CSS.escape(vehicle.id)}"]`);
    if (!card) {
      card = $("#vehicle-template").content.firstElementChild.cloneNode(true);
      card.dataset.vehicle = vehicle.id;
      main.appendChild(card);
    }
    $(".vehicle-id", card).textContent = vehicle.id;
    const state = $(".state", card);
    state.textContent = vehicle.state;
    state.dataset.state = vehicle.state;
    $(".mission", card).textContent = vehicle.prompt ? `Looking for: ${vehicle.prompt}` : "";
    renderCandidates(card, vehicle);
  }
  for (const card of main.querySelectorAll("section.vehicle")) {
    if (!seen.has(card.dataset.vehicle)) card.remove();
  }
  $("#no-vehicles").hidden = data.vehicles.length > 0;
  tick();
}

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
    const verdict = $(".verdict", item);
    verdict.textContent = candidate.verdict;
    verdict.dataset.verdict = candidate.verdict;
    $(".status", item).textContent = candidate.status;
    item.dataset.status = candidate.status;
    $(".justification", item).textContent = candidate.justification || "(no justification)";
    $(".position", item).textContent = formatPosition(candidate.position);
    const open = candidate.status === "awaiting";
    for (const button of item.querySelectorAll(".decide button")) button.disabled = !open || item.dataset.sent === "1";
    if (!open) $(".decision", item).textContent = candidate.status;
    const crop = $(".crop", item);
    crop.hidden = !candidate.crop_url;
    $(".no-crop", item).hidden = Boolean(candidate.crop_url);
    if (candidate.crop_url) loadCrop(crop, candidate.crop_url);
  }
  for (const item of box.querySelectorAll("article.candidate")) {
    if (!seen.has(item.dataset.candidate)) item.remove();
  }
}

async function loadCrop(img, url) {
  if (cropUrls.has(url)) {
    img.src = cropUrls.get(url);
    return;
  }
  cropUrls.set(url, ""); // one fetch per crop
  const response = await fetch(url, { headers: authHeaders() });
  if (!response.ok) {
    cropUrls.delete(url);
    return;
  }
  const objectUrl = URL.createObjectURL(await response.blob());
  cropUrls.set(url, objectUrl);
  img.src = objectUrl;
}

function tick() {
  const extra = elapsed();
  for (const vehicle of snapshot.vehicles) {
    const card = document.querySelector(`section.vehicle[data-vehicle="${CSS.escape(vehicle.id)}"]`);
    if (!card) continue;
    $(".seen", card).textContent = `last report ${formatAge(vehicle.age_s + extra)}`;
    for (const candidate of vehicle.candidates) {
      const item = card.querySelector(`article[data-candidate="${CSS.escape(candidate.id)}"]`);
      if (item) $(".age", item).textContent = `seen ${formatAge(candidate.age_s + extra)}`;
    }
  }
}

async function decide(vehicleId, candidateId, decision, item) {
  for (const button of item.querySelectorAll(".decide button")) button.disabled = true;
  item.dataset.sent = "1";
  const note = $(".decision", item);
  note.textContent = `${decision} sent…`;
  // The API's one decision endpoint; require_awaiting: 409 instead of deciding on a candidate gone stale.
  const url = `/v1/vehicles/${encodeURIComponent(vehicleId)}/decisions?require_awaiting=true`;
  const response = await fetch(url, {
    method: "POST",
    headers: authHeaders({ "Content-Type": "application/json" }),
    body: JSON.stringify({ candidate_id: candidateId, action: decision, note: "supervisor page" }),
  });
  if (response.ok) {
    note.textContent = `${decision} sent, waiting for the vehicle`;
    return;
  }
  item.dataset.sent = "";
  const detail = await response.json().catch(() => ({}));
  note.textContent = `not sent: ${detail.detail || response.status}`;
  for (const button of item.querySelectorAll(".decide button")) button.disabled = false;
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
