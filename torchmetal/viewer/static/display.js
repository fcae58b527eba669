// sRGB display of linear images: exposure, clip to [0, 1], IEC 61966-2-1 encoding, 8-bit rounding.
//
// Exact rounding without a pow per value: THR[k] is the linear value where code k begins (the
// decoded value of (k - 0.5) / 255); a table over [0, 1] in N bins gives the code at each bin's
// start, and since no bin holds two thresholds (bin 1/8192 < the smallest gap 1/(255 * 12.92)),
// one comparison finishes it.

export function srgbToLinear(x) {
  return x <= 0.04045 ? x / 12.92 : Math.pow((x + 0.055) / 1.055, 2.4);
}

export function linearToSrgb(x) {
  return x <= 0.0031308 ? 12.92 * x : 1.055 * Math.pow(x, 1 / 2.4) - 0.055;
}

const N = 8192;
const THR = new Float64Array(257);
THR[0] = -Infinity;
for (let k = 1; k < 256; k++) THR[k] = srgbToLinear((k - 0.5) / 255);
THR[256] = Infinity;
const LUT = new Uint8Array(N + 1);
for (let i = 0, c = 0; i <= N; i++) {
  while (c < 255 && THR[c + 1] <= i / N) c++;
  LUT[i] = c;
}
/** 8-bit linear → linear (the inverse curve at each code). */
export const DECODE8 = Float32Array.from({ length: 256 }, (_, k) => srgbToLinear(k / 255));

export function encode8(v) {
  if (!(v > 0)) return 0; // also NaN
  if (v >= 1) return 255;
  let c = LUT[(v * N) | 0];
  if (v >= THR[c + 1]) c++;
  return c;
}

/**
 * Write planar linear RGB ``lin`` (3, H, W) times ``exposure`` as sRGB into RGBA ``rgba``
 * (H, W, 4), columns [x0, x1) only.
 */
export function encodeInto(lin, width, height, exposure, rgba, x0 = 0, x1 = width) {
  const plane = width * height;
  for (let y = 0; y < height; y++) {
    const row = y * width;
    for (let x = x0; x < x1; x++) {
      const i = row + x, o = 4 * i;
      rgba[o] = encode8(lin[i] * exposure);
      rgba[o + 1] = encode8(lin[i + plane] * exposure);
      rgba[o + 2] = encode8(lin[i + 2 * plane] * exposure);
      rgba[o + 3] = 255;
    }
  }
}

/** An 8-bit sRGB image (RGBA ImageData bytes) as planar linear RGB (3, H, W). */
export function decodeRGBA(rgba, width, height) {
  const plane = width * height;
  const out = new Float32Array(3 * plane);
  for (let i = 0; i < plane; i++) {
    out[i] = DECODE8[rgba[4 * i]];
    out[i + plane] = DECODE8[rgba[4 * i + 1]];
    out[i + 2 * plane] = DECODE8[rgba[4 * i + 2]];
  }
  return out;
}
