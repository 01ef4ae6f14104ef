// Small column-major 4x4 matrix helpers (WebGL's layout) and the cameras of the player.
// A camera is {R: 3x3 row-major cam_from_world rotation, t: [3], fx, fy, cx, cy}: OpenCV axes
// (x right, y down, z forward), pixel centres at integer coordinates, as holocap's cameras.

export function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
export function add(a, b) { return [a[0] + b[0], a[1] + b[1], a[2] + b[2]]; }
export function scale(a, s) { return [a[0] * s, a[1] * s, a[2] * s]; }
export function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
export function cross(a, b) {
  return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
}
export function norm(a) { return Math.sqrt(dot(a, a)); }
export function normalize(a) { const n = norm(a) || 1; return scale(a, 1 / n); }

// cam_from_world of a camera at `eye` looking at `target` with image-up along `up`.
export function lookAt(eye, target, up) {
  const z = normalize(sub(target, eye));
  let x = cross(z, up);
  if (norm(x) < 1e-9) x = cross(z, Math.abs(z[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]);
  x = normalize(x);
  const y = cross(z, x);
  const R = [x, y, z];
  return { R, t: [-dot(x, eye), -dot(y, eye), -dot(z, eye)] };
}

export function cameraCentre(cam) {
  const { R, t } = cam;  // centre = -R^T t
  return [0, 1, 2].map((j) => -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]));
}

// The 4x4 view matrix (world -> camera, OpenCV axes), column-major.
export function viewMatrix(cam) {
  const { R, t } = cam;
  return new Float32Array([
    R[0][0], R[1][0], R[2][0], 0, R[0][1], R[1][1], R[2][1], 0,
    R[0][2], R[1][2], R[2][2], 0, t[0], t[1], t[2], 1]);
}

// Camera coordinates -> clip space for a W x H target: pixel u = fx x / z + cx maps to the
// centre of pixel column u (WebGL's pixel centres sit at half integers).
export function projectionMatrix(cam, W, H, near, far) {
  const a = (far + near) / (far - near), b = -2 * far * near / (far - near);
  return new Float32Array([
    2 * cam.fx / W, 0, 0, 0,
    0, -2 * cam.fy / H, 0, 0,
    2 * (cam.cx + 0.5) / W - 1, 1 - 2 * (cam.cy + 0.5) / H, a, 1,
    0, 0, b, 0]);
}

export function multiply(a, b) {
  const out = new Float32Array(16);
  for (let c = 0; c < 4; ++c)
    for (let r = 0; r < 4; ++r) {
      let s = 0;
      for (let k = 0; k < 4; ++k) s += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = s;
    }
  return out;
}

// A capture camera of the manifest seen on a W x H canvas: its pinhole core scaled to the
// canvas width, centred vertically when the aspect ratios differ.
export function captureCamera(c, W, H) {
  const m = c.cam_from_world;
  const s = W / c.width;
  const [fx, fy, cx, cy] = c.pinhole;
  return {
    R: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
    t: [m[3], m[7], m[11]],
    fx: fx * s, fy: fy * s,
    cx: (cx + 0.5) * s - 0.5,
    cy: (cy + 0.5) * s - 0.5 + (H - c.height * s) / 2,
  };
}
