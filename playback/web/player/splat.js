// Draws a decoded splat frame as holocap's native rasteriser does (splat/kernels.cpp): each
// Gaussian projected by EWA splatting through the camera's pinhole (the tangent clamped to 1.3x
// the field of view, 0.3 px^2 added to the 2D covariance), its colour from the spherical
// harmonics seen from the camera's centre (+0.5, clamped at 0), drawn in the box where its
// alpha reaches 1/255, alpha = min(0.99, opacity exp(power)) with smaller alphas skipped. The
// Gaussians are sorted by depth (a counting sort of 16-bit keys) whenever the frame or the view
// changes and drawn back to front as instanced quads, premultiplied: the same sum as the native
// front-to-back compositing (which only stops once less than 1e-4 of the light is left).
import { compile } from './mesh.js';

const VERTEX = `#version 300 es
precision highp float;
layout(location = 0) in vec2 corner;
layout(location = 1) in vec4 meanExtent;    // pixels: centre u, v and half-sides of the box
layout(location = 2) in vec4 conicOpacity;  // inverse 2D covariance a, b, c and opacity
layout(location = 3) in vec3 colour;        // RGB
uniform vec2 canvas;
flat out vec4 vConic;
flat out vec2 vMean;
flat out vec3 vColour;
void main() {
  vec2 p = meanExtent.xy + corner * meanExtent.zw;
  vConic = conicOpacity;
  vMean = meanExtent.xy;
  vColour = colour;
  gl_Position = vec4((p.x + 0.5) / canvas.x * 2.0 - 1.0, 1.0 - (p.y + 0.5) / canvas.y * 2.0, 0.0, 1.0);
}`;

const FRAGMENT = `#version 300 es
precision highp float;
flat in vec4 vConic;
flat in vec2 vMean;
flat in vec3 vColour;
uniform float canvasHeight;
out vec4 outColour;
void main() {
  vec2 d = vec2(gl_FragCoord.x - 0.5, canvasHeight - gl_FragCoord.y - 0.5) - vMean;
  float power = -0.5 * (vConic.x * d.x * d.x + vConic.z * d.y * d.y) - vConic.y * d.x * d.y;
  if (power > 0.0) discard;
  float alpha = min(0.99, vConic.w * exp(power));
  if (alpha < 1.0 / 255.0) discard;
  outColour = vec4(vColour * alpha, alpha);
}`;

const MIN_ALPHA = 1 / 255, LOW_PASS_PX2 = 0.3, NEAR_M = 0.01;
const FLOATS = 11;  // per instance: mean (2), extent (2), conic (3), opacity, colour (3)

// The real spherical-harmonic basis up to `degree` at a unit direction (as splat/kernels.cpp).
function shBasis(degree, x, y, z, out) {
  out[0] = 0.28209479177387814;
  if (degree < 1) return;
  out[1] = -0.4886025119029199 * y;
  out[2] = 0.4886025119029199 * z;
  out[3] = -0.4886025119029199 * x;
  if (degree < 2) return;
  const xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  out[4] = 1.0925484305920792 * xy;
  out[5] = -1.0925484305920792 * yz;
  out[6] = 0.31539156525252005 * (2 * zz - xx - yy);
  out[7] = -1.0925484305920792 * xz;
  out[8] = 0.5462742152960396 * (xx - yy);
  if (degree < 3) return;
  out[9] = -0.5900435899266435 * y * (3 * xx - yy);
  out[10] = 2.890611442640554 * xy * z;
  out[11] = -0.4570457994644658 * y * (4 * zz - xx - yy);
  out[12] = 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy);
  out[13] = -0.4570457994644658 * x * (4 * zz - xx - yy);
  out[14] = 1.445305721320277 * z * (xx - yy);
  out[15] = -0.5900435899266435 * x * (xx - 3 * yy);
}

// World covariances Sigma = R S S R^T of every Gaussian (xx, xy, xz, yy, yz, zz): the view does
// not change them.
function covariances(g) {
  const sigma = new Float64Array(6 * g.count);
  for (let i = 0; i < g.count; ++i) {
    const [w, x, y, z] = g.rotation.subarray(4 * i, 4 * i + 4);
    const r = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
               2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
               2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)];
    const m = new Array(9);
    for (let row = 0; row < 3; ++row)
      for (let col = 0; col < 3; ++col) m[3 * row + col] = r[3 * row + col] * g.scale[3 * i + col];
    const dot = (a, b) => m[3 * a] * m[3 * b] + m[3 * a + 1] * m[3 * b + 1] + m[3 * a + 2] * m[3 * b + 2];
    sigma.set([dot(0, 0), dot(0, 1), dot(0, 2), dot(1, 1), dot(1, 2), dot(2, 2)], 6 * i);
  }
  return sigma;
}

export class SplatRenderer {
  constructor(gl) {
    this.gl = gl;
    this.program = compile(gl, VERTEX, FRAGMENT);
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const quad = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, quad);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    this.instances = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.instances);
    const stride = FLOATS * 4;
    for (const [location, size, offset] of [[1, 4, 0], [2, 4, 4], [3, 3, 8]]) {
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, size, gl.FLOAT, false, stride, offset * 4);
      gl.vertexAttribDivisor(location, 1);
    }
    gl.bindVertexArray(null);
    this.frame = null;
    this.viewKey = '';
    this.drawn = 0;
  }

  // Projects and sorts the frame's Gaussians for a camera on a W x H canvas; fills the instance
  // buffer back to front.
  project(splats, camera, W, H) {
    const g = splats.expand(), n = g.count;
    if (!splats.sigma) splats.sigma = covariances(g);
    const sigma = splats.sigma, { R, t, fx, fy, cx, cy } = camera;
    const centre = [0, 1, 2].map((j) => -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]));
    const limitU = 1.3 * 0.5 * W / fx, limitV = 1.3 * 0.5 * H / fy, cap = 2 * (W + H);
    const k = (g.degree + 1) ** 2, basis = new Float64Array(16);
    const values = new Float32Array(FLOATS * n), depth = new Float32Array(n), drawn = [];
    for (let i = 0; i < n; ++i) {
      const wx = g.position[3 * i], wy = g.position[3 * i + 1], wz = g.position[3 * i + 2];
      const px = R[0][0] * wx + R[0][1] * wy + R[0][2] * wz + t[0];
      const py = R[1][0] * wx + R[1][1] * wy + R[1][2] * wz + t[1];
      const z = R[2][0] * wx + R[2][1] * wy + R[2][2] * wz + t[2];
      if (!(z > NEAR_M)) continue;
      const u = Math.min(limitU, Math.max(-limitU, px / z)), v = Math.min(limitV, Math.max(-limitV, py / z));
      // T = J W (rows t0, t1), J the EWA Jacobian at the clamped tangent; cov = T Sigma T^T.
      const j00 = fx / z, j02 = -fx * u / z, j11 = fy / z, j12 = -fy * v / z;
      const t00 = j00 * R[0][0] + j02 * R[2][0], t01 = j00 * R[0][1] + j02 * R[2][1];
      const t02 = j00 * R[0][2] + j02 * R[2][2], t10 = j11 * R[1][0] + j12 * R[2][0];
      const t11 = j11 * R[1][1] + j12 * R[2][1], t12 = j11 * R[1][2] + j12 * R[2][2];
      const o6 = 6 * i, sxx = sigma[o6], sxy = sigma[o6 + 1], sxz = sigma[o6 + 2];
      const syy = sigma[o6 + 3], syz = sigma[o6 + 4], szz = sigma[o6 + 5];
      const a0 = t00 * sxx + t01 * sxy + t02 * sxz, a1 = t00 * sxy + t01 * syy + t02 * syz;
      const a2 = t00 * sxz + t01 * syz + t02 * szz, b0 = t10 * sxx + t11 * sxy + t12 * sxz;
      const b1 = t10 * sxy + t11 * syy + t12 * syz, b2 = t10 * sxz + t11 * syz + t12 * szz;
      const a = a0 * t00 + a1 * t01 + a2 * t02 + LOW_PASS_PX2;
      const b = a0 * t10 + a1 * t11 + a2 * t12;
      const c = b0 * t10 + b1 * t11 + b2 * t12 + LOW_PASS_PX2;
      const det = a * c - b * b;
      if (!(det > 0) || !Number.isFinite(det)) continue;
      const mu = fx * px / z + cx, mv = fy * py / z + cy;
      const o = g.opacity[i], k2 = 2 * Math.log(o / MIN_ALPHA);
      if (!(k2 > 0)) continue;
      const eu = Math.sqrt(k2 * a), ev = Math.sqrt(k2 * c);
      if (!Number.isFinite(mu) || !Number.isFinite(mv) || mu + eu < -0.5 || mv + ev < -0.5 ||
          mu - eu > W - 0.5 || mv - ev > H - 0.5) continue;
      const dx = wx - centre[0], dy = wy - centre[1], dz = wz - centre[2];
      const length = Math.hypot(dx, dy, dz), inv = length > 0 ? 1 / length : 0;
      shBasis(g.degree, dx * inv, dy * inv, dz * inv, basis);
      const at = FLOATS * i;
      values[at] = mu;
      values[at + 1] = mv;
      values[at + 2] = Math.min(eu, cap);
      values[at + 3] = Math.min(ev, cap);
      values[at + 4] = c / det;
      values[at + 5] = -b / det;
      values[at + 6] = a / det;
      values[at + 7] = o;
      for (let channel = 0; channel < 3; ++channel) {
        let value = 0.5;
        for (let q = 0; q < k; ++q) value += basis[q] * g.sh[(i * k + q) * 3 + channel];
        values[at + 10 - channel] = Math.max(value, 0);  // stored B, G, R; drawn R, G, B
      }
      depth[i] = z;
      drawn.push(i);
    }
    // Back to front: a counting sort of the depths quantised to 16 bits (farthest first).
    let near = Infinity, far = -Infinity;
    for (const i of drawn) { near = Math.min(near, depth[i]); far = Math.max(far, depth[i]); }
    const keys = new Uint16Array(drawn.length), counts = new Uint32Array(65537);
    const range = far > near ? 65535 / (far - near) : 0;
    drawn.forEach((i, d) => { keys[d] = Math.floor((far - depth[i]) * range); ++counts[keys[d] + 1]; });
    for (let key = 1; key <= 65536; ++key) counts[key] += counts[key - 1];
    const sorted = new Float32Array(FLOATS * drawn.length);
    drawn.forEach((i, d) => sorted.set(values.subarray(FLOATS * i, FLOATS * i + FLOATS), FLOATS * counts[keys[d]]++));
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.instances);
    gl.bufferData(gl.ARRAY_BUFFER, sorted, gl.DYNAMIC_DRAW);
    this.drawn = drawn.length;
  }

  draw(splats, camera, W, H) {
    const gl = this.gl;
    const key = JSON.stringify([camera, W, H]);
    if (this.frame !== splats || this.viewKey !== key) {
      if (this.frame && this.frame !== splats) {  // the frame drawn before keeps its codes only
        this.frame.gaussians = null;
        this.frame.sigma = null;
      }
      this.project(splats, camera, W, H);
      this.frame = splats;
      this.viewKey = key;
    }
    gl.useProgram(this.program);
    gl.uniform2f(gl.getUniformLocation(this.program, 'canvas'), W, H);
    gl.uniform1f(gl.getUniformLocation(this.program, 'canvasHeight'), H);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);  // premultiplied, each over those behind it
    gl.bindVertexArray(this.vao);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, this.drawn);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);
  }
}
