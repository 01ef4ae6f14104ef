// Lines: the floor grid (the plane through the bounds' lowest point, normal to "up") and the
// capture cameras as frusta (their image corners at a fixed distance).
import { compile } from './mesh.js';
import { add, cross, dot, normalize, scale } from './math.js';

const VERTEX = `#version 300 es
in vec3 position;
in vec3 color;
uniform mat4 view, projection;
out vec3 vColor;
void main() { vColor = color; gl_Position = projection * view * vec4(position, 1.0); }`;
const FRAGMENT = `#version 300 es
precision highp float;
in vec3 vColor;
out vec4 colour;
void main() { colour = vec4(vColor, 1.0); }`;

export function floorLines(manifest) {
  const up = normalize(manifest.up);
  const lo = manifest.bounds.min, hi = manifest.bounds.max;
  const centre = scale(add(lo, hi), 0.5);
  const height = Math.min(dot(lo, up), dot(hi, up));
  const origin = add(centre, scale(up, height - dot(centre, up)));
  let a = cross(up, [1, 0, 0]);
  if (Math.hypot(...a) < 0.1) a = cross(up, [0, 1, 0]);
  a = normalize(a);
  const b = cross(up, a);
  const lines = [], colors = [];
  const half = 3, stepM = 0.5;
  for (let i = -half; i <= half + 1e-9; i += stepM) {
    const shade = Math.abs(i) < 1e-9 ? 0.45 : 0.25;
    lines.push(add(origin, add(scale(a, i), scale(b, -half))), add(origin, add(scale(a, i), scale(b, half))));
    lines.push(add(origin, add(scale(b, i), scale(a, -half))), add(origin, add(scale(b, i), scale(a, half))));
    for (let k = 0; k < 4; ++k) colors.push([shade, shade, shade]);
  }
  return { lines, colors };
}

export function frustumLines(manifest, selected) {
  const lines = [], colors = [];
  manifest.cameras.forEach((c, index) => {
    const m = c.cam_from_world;
    const R = [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]];
    const t = [m[3], m[7], m[11]];
    const toWorld = (p) => [0, 1, 2].map((j) => R[0][j] * (p[0] - t[0]) + R[1][j] * (p[1] - t[1]) + R[2][j] * (p[2] - t[2]));
    const [fx, fy, cx, cy] = c.pinhole || [c.width, c.width, c.width / 2, c.height / 2];
    const depth = 0.3;
    const corner = (u, v) => toWorld([(u - cx) / fx * depth, (v - cy) / fy * depth, depth]);
    const o = toWorld([0, 0, 0]);
    const k = [corner(-0.5, -0.5), corner(c.width - 0.5, -0.5), corner(c.width - 0.5, c.height - 0.5), corner(-0.5, c.height - 0.5)];
    const colour = index === selected ? [1.0, 0.75, 0.2] : [0.3, 0.6, 1.0];
    for (let i = 0; i < 4; ++i) {
      lines.push(o, k[i], k[i], k[(i + 1) % 4]);
      for (let j = 0; j < 4; ++j) colors.push(colour);
    }
    const up = toWorld([0, -0.25 * depth * c.height / fy, depth]);
    lines.push(k[0], up, up, k[1]);
    for (let j = 0; j < 4; ++j) colors.push(colour);
  });
  return { lines, colors };
}

export class LineRenderer {
  constructor(gl) {
    this.gl = gl;
    this.program = compile(gl, VERTEX, FRAGMENT);
    this.vao = gl.createVertexArray();
    this.position = gl.createBuffer();
    this.color = gl.createBuffer();
    this.count = 0;
  }

  set({ lines, colors }) {
    const gl = this.gl;
    gl.bindVertexArray(this.vao);
    for (const [name, buffer, data] of [['position', this.position, lines], ['color', this.color, colors]]) {
      const location = gl.getAttribLocation(this.program, name);
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(data.flat()), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, 3, gl.FLOAT, false, 0, 0);
    }
    gl.bindVertexArray(null);
    this.count = lines.length;
  }

  draw(view, projection) {
    const gl = this.gl;
    gl.useProgram(this.program);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.program, 'view'), false, view);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.program, 'projection'), false, projection);
    gl.enable(gl.DEPTH_TEST);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.LINES, 0, this.count);
    gl.bindVertexArray(null);
  }
}


