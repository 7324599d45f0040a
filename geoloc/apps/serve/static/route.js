// The route player: posts a route's frames and its odometry.csv to /localize/route and plays the track it answers
// on a north-up map of the tiles the answers named. It runs after page.js and uses its helpers ($, setText, fmt,
// place, appendSettings, send). Everything shown is set with textContent or drawn on the canvas, never parsed as
// markup, so a file name stays text.
"use strict";

const FRAME_SUFFIXES = [".jpg", ".jpeg", ".png"];  // what localize.py takes from a route's folder
const CHI2_95 = 5.991;  // chi-square with 2 degrees of freedom at 95%: the ellipse's squared Mahalanobis radius
const EARTH_M = 6371008.8;  // mean earth radius, for the equirectangular approximation about the first estimate
const STEP_MS = 400;  // a frame every 0.4 s when playing
const MARGIN_PX = 16;
const BLUE = "#06f", ORANGE = "#f80";  // the track, the frames' own answers
const MIN_SPAN_M = 50;  // the least the map shows across, so that a route standing still is not drawn at one point
let route = null;  // the answer being shown, with its plane and its tile images
let playing = null;  // the play timer, while playing

function showRouteError(message) {
  setText("route-error", message);
  setText("route-status", "");
}

function byName(a, b) { return a.name < b.name ? -1 : a.name > b.name ? 1 : 0; }

// The chosen files as a route: {frames (JPEG / PNG, sorted by name), odometry (the .csv), left (other files)}, or
// {refusal}. Where several .csv files are chosen, the one named odometry.csv is the odometry (a synthetic route's
// folder also holds truth.csv).
function routeOf(files) {
  const all = [...files];
  if (all.length === 0) {
    return { refusal: "choose a route's files first: its frames (JPEG or PNG) and its odometry.csv" };
  }
  const csvs = all.filter((f) => f.name.toLowerCase().endsWith(".csv"));
  const frames = all.filter((f) => FRAME_SUFFIXES.some((s) => f.name.toLowerCase().endsWith(s))).sort(byName);
  const named = csvs.filter((f) => f.name === "odometry.csv");
  const odometry = csvs.length === 1 ? csvs[0] : named.length === 1 ? named[0] : null;
  if (csvs.length === 0) {
    return { refusal: "no odometry: choose the route's odometry.csv (frame,distance_m,heading_change_deg) " +
                      "together with its frames" };
  }
  if (odometry === null) {
    return { refusal: `${csvs.length} .csv files (${csvs.map((f) => f.name).sort().join(", ")}), none of them ` +
                      "named odometry.csv: choose the route's one odometry file together with its frames" };
  }
  if (frames.length === 0) {
    return { refusal: `no frames: choose the route's JPEG or PNG frames together with ${odometry.name}` };
  }
  return { frames, odometry, left: all.filter((f) => f !== odometry && !frames.includes(f)) };
}

function chooseRoute() {
  stop();
  const { refusal, frames, odometry, left } = routeOf($("route-files").files);
  if (refusal !== undefined) { showRouteError(refusal); return; }
  setText("route-error", "");
  const also = left.length ? ` (left out: ${left.map((f) => f.name).join(", ")})` : "";
  setText("route-status", `${frames.length} frames and ${odometry.name}${also}`);
}

// A position of the answer ({lat, lon} or {x_m, y_m}) as [east, north] metres about `origin`, one of its kind
function toPlane(where, origin) {
  if ("x_m" in where) return [where.x_m - origin.x_m, where.y_m - origin.y_m];
  const rad = Math.PI / 180;
  return [(where.lon - origin.lon) * rad * EARTH_M * Math.cos(origin.lat * rad),
          (where.lat - origin.lat) * rad * EARTH_M];
}

function median(values) {
  const sorted = [...values].sort((a, b) => a - b);
  const mid = sorted.length >> 1;
  return sorted.length % 2 ? sorted[mid] : (sorted[mid - 1] + sorted[mid]) / 2;
}

// The side of the square a tile without a ground extent is drawn as: the median width of those with one, else the
// median distance from each tile to its nearest neighbour (a gallery's tiles abut theirs), else 50 m
function fallbackSide(tiles) {
  const widths = tiles.filter((t) => Array.isArray(t.extent_m)).map((t) => t.extent_m[1]);
  if (widths.length) return median(widths);
  const nearest = tiles.map((t) => {
    let best = Infinity;
    for (const u of tiles) if (u !== t) best = Math.min(best, Math.hypot(u.at[0] - t.at[0], u.at[1] - t.at[1]));
    return best;
  }).filter((d) => Number.isFinite(d) && d > 0);
  return nearest.length ? median(nearest) : 50;
}

// The map's view: metres to canvas pixels, north up, fitting the track, the frames' answers and their top-1 tiles
function viewOf(canvas, boxes) {
  const east = boxes.flatMap((b) => [b[0], b[2]]), north = boxes.flatMap((b) => [b[1], b[3]]);
  const [e0, e1, n0, n1] = [Math.min(...east), Math.max(...east), Math.min(...north), Math.max(...north)];
  const scale = Math.min((canvas.width - 2 * MARGIN_PX) / Math.max(e1 - e0, MIN_SPAN_M),
                         (canvas.height - 2 * MARGIN_PX) / Math.max(n1 - n0, MIN_SPAN_M));
  const [ce, cn] = [(e0 + e1) / 2, (n0 + n1) / 2];
  return { scale, x: (e) => canvas.width / 2 + (e - ce) * scale, y: (n) => canvas.height / 2 - (n - cn) * scale };
}

function planeOf(answer) {
  const origin = answer.frames[0].position;
  const track = answer.frames.map((f) => toPlane(f.position, origin));
  const own = answer.frames.map((f) => toPlane(f.frame_answer, origin));
  const tiles = answer.tiles.map((t) => ({ ...t, at: toPlane(t, origin) }));
  const side = fallbackSide(tiles);
  for (const t of tiles) {
    const [h, w] = Array.isArray(t.extent_m) ? t.extent_m : [side, side];
    t.box = [t.at[0] - w / 2, t.at[1] - h / 2, t.at[0] + w / 2, t.at[1] + h / 2];
  }
  const top1 = new Set(answer.answers.map((a) => a.topk && a.topk[0] && a.topk[0].row));
  const boxes = [...track, ...own].map(([e, n]) => [e, n, e, n])
    .concat(tiles.filter((t) => top1.has(t.row)).map((t) => t.box));
  return { track, own, tiles, view: viewOf($("route-map"), boxes) };
}

// The 95% ellipse of a 2 x 2 east/north covariance: its radii (metres) and the major axis' angle from east
function ellipse(cov) {
  const [a, b, c] = [cov[0][0], cov[0][1], cov[1][1]];
  const mid = (a + c) / 2, half = Math.sqrt(((a - c) / 2) ** 2 + b ** 2);
  return { major: Math.sqrt(CHI2_95 * (mid + half)), minor: Math.sqrt(CHI2_95 * Math.max(mid - half, 0)),
           angle: 0.5 * Math.atan2(2 * b, a - c) };
}

// Stroke the path `trace` adds to in `colour` over a white halo, so that it shows on any tile
function stroke(ctx, trace, colour) {
  for (const [style, width] of [["#fff", 5], [colour, 2]]) {
    ctx.strokeStyle = style;
    ctx.lineWidth = width;
    ctx.beginPath();
    trace();
    ctx.stroke();
  }
}

function draw() {
  const canvas = $("route-map");
  const ctx = canvas.getContext("2d");
  const { plane, images, answer } = route;
  const { view } = plane;
  const shown = Number($("route-frame").value);
  ctx.fillStyle = "#fff";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  let drawn = 0;
  for (const tile of plane.tiles) {
    const image = images.get(tile.row);
    if (!image || !image.complete || image.naturalWidth === 0) continue;
    const [e0, n0, e1, n1] = tile.box;
    ctx.drawImage(image, view.x(e0), view.y(n1), (e1 - e0) * view.scale, (n1 - n0) * view.scale);
    drawn += 1;
  }
  const points = (list) => list.slice(0, shown + 1).map(([e, n]) => [view.x(e), view.y(n)]);
  stroke(ctx, () => points(plane.track).forEach(([x, y]) => ctx.lineTo(x, y)), BLUE);  // the filtered track
  stroke(ctx, () => {  // each frame's own answer, up to the shown frame: a cross
    for (const [x, y] of points(plane.own)) {
      ctx.moveTo(x - 5, y - 5); ctx.lineTo(x + 5, y + 5);
      ctx.moveTo(x - 5, y + 5); ctx.lineTo(x + 5, y - 5);
    }
  }, ORANGE);
  const [x, y] = points(plane.track)[shown];
  const frame = answer.frames[shown];
  const { major, minor, angle } = ellipse(frame.covariance_m2);
  // y grows downward on the canvas, so the angle from east turns the other way
  stroke(ctx, () => ctx.ellipse(x, y, Math.max(major * view.scale, 1), Math.max(minor * view.scale, 1), -angle, 0,
                                2 * Math.PI), BLUE);
  const rad = (Number(frame.heading_deg) || 0) * Math.PI / 180;  // clockwise from north
  stroke(ctx, () => { ctx.moveTo(x, y); ctx.lineTo(x + 20 * Math.sin(rad), y - 20 * Math.cos(rad)); }, BLUE);
  stroke(ctx, () => ctx.arc(x, y, 4, 0, 2 * Math.PI), BLUE);
  ctx.fillStyle = BLUE;
  ctx.fill();
  canvas.dataset.frame = String(shown);
  canvas.dataset.tilesDrawn = String(drawn);
}

function area(m2) {
  return m2 >= 1e4 ? `${fmt(m2 / 1e4, 2)} ha` : `${fmt(m2, 0)} m²`;
}

function show(index) {
  $("route-frame").value = String(index);
  const frame = route.answer.frames[index];
  const whole = frame.region_95_whole_gallery === true ? " (the whole gallery)" : "";
  setText("route-estimate", `${frame.frame} (frame ${index + 1} of ${route.answer.frames.length}): ` +
          `${place(frame.position)}, heading ${fmt(frame.heading_deg, 1)}° from north; 95% region ` +
          `${area(frame.region_95_area_m2)}${whole}; tracked mass ${fmt(frame.tracked_mass, 3)}`);
  draw();
}

function stop() {
  if (playing !== null) clearInterval(playing);
  playing = null;
  setText("route-play", "Play");
}

function play() {
  if (playing !== null) { stop(); return; }
  const last = route.answer.frames.length - 1;
  if (Number($("route-frame").value) >= last) show(0);
  setText("route-play", "Pause");
  playing = setInterval(() => {
    const next = Number($("route-frame").value) + 1;
    if (next > last) { stop(); return; }
    show(next);
  }, STEP_MS);
}

function showRoute(answer) {
  const images = new Map();
  route = { answer, images, plane: planeOf(answer) };
  const mine = route;
  for (const tile of answer.tiles) {
    const image = new Image();
    image.onload = () => { if (route === mine) draw(); };  // a later route's answer is not redrawn by this one's
    image.src = `/tiles/${encodeURIComponent(tile.row)}`;
    images.set(tile.row, image);
  }
  const slider = $("route-frame");
  slider.max = String(answer.frames.length - 1);
  $("route-result").hidden = false;
  show(0);
  setText("route-status", `followed ${answer.frames.length} frames`);
}

async function followRoute() {
  stop();
  const { refusal, frames, odometry } = routeOf($("route-files").files);
  if (refusal !== undefined) { showRouteError(refusal); return; }
  setText("route-error", "");
  const body = new FormData();
  for (const frame of frames) body.append("frames", frame, frame.name);
  body.append("odometry", odometry, odometry.name);
  appendSettings(body, ["fov", "topk", "heading"]);
  setText("route-status", `following ${frames.length} frames ...`);
  await send("/localize/route", body, "route-submit", showRoute, showRouteError);
}

$("route-files").addEventListener("change", chooseRoute);
$("route-submit").addEventListener("click", followRoute);
$("route-play").addEventListener("click", play);
$("route-frame").addEventListener("input", () => { stop(); show(Number($("route-frame").value)); });
