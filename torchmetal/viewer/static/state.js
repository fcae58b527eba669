// View state: the URL fragment <-> the page state <-> the renderer's inputs (docs/design.md §2.1 / 2.4).
//
// Angles in degrees: azimuth from +x towards +y, elevation above the surface plane (z = 0).
// Distances are in multiples of the surface's longer side ("extent").
// Light: "point" at distance ld along (laz, lel), radiant intensity li * lc * (ld * extent)^2
// (so li is the irradiance at the sample's centre); "dir" a directional light with irradiance li * lc.
// Camera: "ortho" an orthographic direction (w = 0), "point" a position at distance cd (w = 1).

export const DEFAULTS = Object.freeze({
  lt: "point", laz: 30, lel: 50, ld: 1.5, li: 1, lc: [1, 1, 1],
  ex: 1,
  ct: "ortho", caz: 0, cel: 90, cd: 2,
  fl: 1,
  shot: -1, ab: "render", sp: 0.5,
});

const NUMBERS = ["laz", "lel", "ld", "li", "ex", "caz", "cel", "cd", "fl", "shot", "sp"];
const CHOICES = { lt: ["point", "dir"], ct: ["ortho", "point"], ab: ["render", "side", "split"] };
const MIN_EL = 0.5; // lights and cameras stay above the surface (z > 0)
const RAD = Math.PI / 180;

export function clampState(s) {
  const c = { ...s, lc: [...s.lc] };
  const wrap = (a) => ((((a + 180) % 360) + 360) % 360) - 180;
  c.laz = wrap(c.laz); c.caz = wrap(c.caz);
  c.lel = Math.min(90, Math.max(MIN_EL, c.lel));
  c.cel = Math.min(90, Math.max(MIN_EL, c.cel));
  c.ld = Math.max(1e-3, c.ld); c.cd = Math.max(1e-3, c.cd);
  c.li = Math.max(0, c.li); c.ex = Math.max(0, c.ex);
  c.lc = c.lc.map((v) => Math.max(0, v));
  c.fl = c.fl ? 1 : 0;
  c.sp = Math.min(1, Math.max(0, c.sp));
  c.shot = Math.trunc(c.shot);
  return c;
}

/** State from a URL fragment ("#laz=30&lel=50&…"); unknown or malformed keys keep their defaults. */
export function readHash(hash) {
  const s = { ...DEFAULTS, lc: [...DEFAULTS.lc] };
  const p = new URLSearchParams(hash.replace(/^#/, ""));
  for (const k of NUMBERS) {
    if (p.has(k) && Number.isFinite(Number(p.get(k))) && p.get(k) !== "") s[k] = Number(p.get(k));
  }
  for (const [k, allowed] of Object.entries(CHOICES)) {
    if (allowed.includes(p.get(k))) s[k] = p.get(k);
  }
  if (p.has("lc")) {
    const v = p.get("lc").split(",").map(Number);
    if (v.length === 3 && v.every(Number.isFinite)) s.lc = v;
  }
  return clampState(s);
}

const short = (v) => String(v); // shortest text that reads back as the same double: a link reproduces the view exactly

export function writeHash(s) {
  const p = new URLSearchParams();
  for (const k of Object.keys(DEFAULTS)) {
    p.set(k, k === "lc" ? s.lc.map(short).join(",") : (typeof s[k] === "number" ? short(s[k]) : s[k]));
  }
  return "#" + p.toString();
}

export function direction(az, el) {
  const a = az * RAD, e = el * RAD;
  return [Math.cos(e) * Math.cos(a), Math.cos(e) * Math.sin(a), Math.sin(e)];
}

/** The renderer's inputs for state ``s``: {light: [4], light_intensity: [3], camera: [4]}. */
export function inputsFromState(s, extent) {
  const l = direction(s.laz, s.lel);
  const c = direction(s.caz, s.cel);
  const r = s.ld * extent;
  const point = s.lt === "point";
  const light = point ? [l[0] * r, l[1] * r, l[2] * r, 1] : [...l, 0];
  const light_intensity = s.lc.map((v) => v * s.li * (point ? r * r : 1));
  const cr = s.cd * extent;
  const camera = s.ct === "point" ? [c[0] * cr, c[1] * cr, c[2] * cr, 1] : [...c, 0];
  return { light, light_intensity, camera };
}

function polar(v) {
  const n = Math.hypot(v[0], v[1], v[2]) || 1;
  return { az: Math.atan2(v[1], v[0]) / RAD, el: Math.asin(Math.min(1, v[2] / n)) / RAD, r: n };
}

/** The state whose inputs are a captured shot's (light, light_intensity, camera). */
export function stateFromShot(s, shot, extent) {
  const out = { ...s };
  const l = polar(shot.light);
  out.laz = l.az; out.lel = l.el;
  const point = shot.light[3] > 0.5;
  out.lt = point ? "point" : "dir";
  if (point) out.ld = l.r / extent;
  const irr = shot.light_intensity.map((v) => v / (point ? l.r * l.r : 1));
  const top = Math.max(...irr);
  out.li = top > 0 ? top : 0;
  out.lc = top > 0 ? irr.map((v) => v / top) : [1, 1, 1];
  const c = polar(shot.camera);
  out.caz = c.az; out.cel = c.el;
  out.ct = shot.camera[3] > 0.5 ? "point" : "ortho";
  if (out.ct === "point") out.cd = c.r / extent;
  return out; // not clamped: a shot's angles are used as they are
}
