// The geoloc page: posts the dropped image to /localize and shows the answer. Everything shown is set with
// textContent or as an attribute of a node made here, never parsed as markup, so an answer or a file name stays text.
// Its helpers ($, setText, fmt, place, appendSettings, send) serve route.js, the route player, too.
"use strict";

const $ = (id) => document.getElementById(id);
const TYPES = ["image/jpeg", "image/png"];
let chosen = null;
let refusal = "choose a street image first (a JPEG or PNG)";  // why nothing can be sent yet
let preview = null;

function setText(id, text) { $(id).textContent = text; }

function showError(message) {
  setText("error", message);
  setText("status", "");
}

function choose(file) {
  setText("error", "");
  if (!file) return;
  setText("filename", file.name);
  if (!TYPES.includes(file.type)) {
    chosen = null;
    refusal = `${file.name} is not a JPEG or PNG image (it is ${file.type || "of an unknown type"}): choose a street image`;
    showError(refusal);
    return;
  }
  chosen = file;
  if (preview) URL.revokeObjectURL(preview);
  preview = URL.createObjectURL(file);
  $("query-preview").src = preview;
  $("query-preview").hidden = false;
}

function fmt(value, digits) {
  return typeof value === "number" && Number.isFinite(value) ? value.toFixed(digits) : String(value);
}

function place(where) {
  if (!where || typeof where !== "object") return "unknown (the gallery has no positions)";
  if ("lat" in where) return `lat ${fmt(where.lat, 6)}, lon ${fmt(where.lon, 6)}`;
  if ("x_m" in where) return `x ${fmt(where.x_m, 1)} m, y ${fmt(where.y_m, 1)} m`;
  return Object.entries(where).map(([k, v]) => `${k} ${fmt(v, 3)}`).join(", ");
}

// The position inside the best tile, as a fraction of its side: a refined pixel when the answer gives one
// ([row, col] in the tile's pixel frame with its size), else the tile centre (retrieval alone answers the tile).
function tileFraction(answer) {
  const refined = answer.refined_position;
  if (refined && Array.isArray(refined.tile_px) && Array.isArray(refined.tile_size_px)) {
    return [refined.tile_px[0] / refined.tile_size_px[0], refined.tile_px[1] / refined.tile_size_px[1]];
  }
  return [0.5, 0.5];
}

function drawBest(answer) {
  const canvas = $("best-tile");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const best = answer.topk && answer.topk[0];
  if (!best) return;
  const tile = new Image();
  tile.onload = () => {
    ctx.drawImage(tile, 0, 0, canvas.width, canvas.height);
    const [fy, fx] = tileFraction(answer);
    const x = fx * canvas.width, y = fy * canvas.height;
    const rad = (Number(answer.heading_deg) || 0) * Math.PI / 180;  // clockwise from north: north is up
    const len = canvas.width * 0.2;
    ctx.strokeStyle = "#ff2a2a"; ctx.fillStyle = "#ff2a2a"; ctx.lineWidth = 3;
    ctx.beginPath(); ctx.moveTo(x, y);
    const tx = x + len * Math.sin(rad), ty = y - len * Math.cos(rad);
    ctx.lineTo(tx, ty); ctx.stroke();
    ctx.beginPath();
    ctx.moveTo(tx, ty);
    ctx.lineTo(tx - 10 * Math.sin(rad - 0.5), ty + 10 * Math.cos(rad - 0.5));
    ctx.lineTo(tx - 10 * Math.sin(rad + 0.5), ty + 10 * Math.cos(rad + 0.5));
    ctx.closePath(); ctx.fill();
    ctx.beginPath(); ctx.arc(x, y, 6, 0, 2 * Math.PI); ctx.fill();
  };
  tile.src = `/tiles/${encodeURIComponent(best.row)}`;
}

// The refined position, with the refiner's calibrated P(within 5 m) where the gallery gives it
function refinedText(refined) {
  let text = place(refined);
  if (typeof refined.confidence_within_5m === "number") {
    text += `; ${(100 * refined.confidence_within_5m).toFixed(1)}% that it is within 5 m, if the tile is right`;
  }
  return text;
}

function showAnswer(answer) {
  $("result").hidden = false;
  if (typeof answer.confidence === "number") {
    let text = `${(100 * answer.confidence).toFixed(1)}% that the best tile is right`;
    if (answer.abstained === true) text += " (below the abstain threshold: the service abstains)";
    setText("confidence", text);
    $("confidence").className = answer.abstained === true ? "abstained" : "";
  } else {
    setText("confidence", "uncalibrated: this gallery gives no confidence for this query " +
                          "(see /health: calibration)");
    $("confidence").className = "";
  }
  setText("heading-out", `${fmt(answer.heading_deg, 1)}° from north (${answer.heading_source})`);
  setText("position", place(answer.position));
  setText("refined", answer.refined_position ? refinedText(answer.refined_position) :
                                               "none (the tile centre is the answer)");
  const list = $("hits");  // the list of tiles ("topk" is the form's number field)
  list.replaceChildren();
  for (const hit of answer.topk || []) {
    const item = document.createElement("li");
    item.className = "hit";
    const img = document.createElement("img");
    img.src = `/tiles/${encodeURIComponent(hit.row)}`;
    img.alt = `tile ${hit.rank}`;
    const caption = document.createElement("div");
    caption.className = "caption";
    caption.textContent = `#${hit.rank} score ${fmt(hit.score, 3)}, heading ${fmt(hit.heading_deg, 0)}°: ` +
                          `${place(hit)} (${hit.path})`;
    item.append(img, caption);
    list.append(item);
  }
  drawBest(answer);
  setText("status", `answered ${answer.image === null || answer.image === undefined ? "the image" : answer.image}`);
}

// The settings fields named in `keys` that are not blank, appended to the form `body`
function appendSettings(body, keys) {
  for (const key of keys) {
    const value = $(key).value.trim();
    if (value !== "") body.append(key, value);
  }
}

// POST the form `body` to `path` with `button` disabled meanwhile, then `show(answer)` with its JSON, or `refuse(text)`
// with the service's 4xx/5xx detail after its status, or why the service could not be reached
async function send(path, body, button, show, refuse) {
  $(button).disabled = true;
  try {
    const response = await fetch(path, { method: "POST", body });
    const answer = await response.json().catch(() => ({ detail: `the service answered ${response.status} without JSON` }));
    if (response.ok) {
      show(answer);
    } else {
      refuse(`${response.status}: ${typeof answer.detail === "string" ? answer.detail : JSON.stringify(answer.detail)}`);
    }
  } catch (err) {
    refuse(`the service could not be reached: ${err}`);
  } finally {
    $(button).disabled = false;
  }
}

async function localize(event) {
  event.preventDefault();
  if (!chosen) { showError(refusal); return; }
  setText("error", "");
  const body = new FormData();
  body.append("image", chosen, chosen.name);
  appendSettings(body, ["fov", "topk", "heading", "heading_prior", "abstain"]);
  setText("status", "localizing ...");
  await send("/localize", body, "submit", showAnswer, showError);
}

const drop = $("drop");
drop.addEventListener("click", () => $("image").click());
drop.addEventListener("keydown", (e) => { if (e.key === "Enter" || e.key === " ") $("image").click(); });
drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
drop.addEventListener("dragleave", () => drop.classList.remove("over"));
drop.addEventListener("drop", (e) => {
  e.preventDefault();
  drop.classList.remove("over");
  choose(e.dataTransfer.files[0]);
});
$("image").addEventListener("change", () => choose($("image").files[0]));
$("query-form").addEventListener("submit", localize);
