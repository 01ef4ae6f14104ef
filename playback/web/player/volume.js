// Ray-marches a decoded volume frame as holocap's native renderer does (neural/raymarch.h,
// MarchPlayback): rays through pixel centres clipped to the box, samples at t_near + k step,
// trilinear reads of the grid (border clamped for a resampled grid, else zero), optical depth
// accumulated front to back, a ray stopped once its transmittance falls below the stream's
// minimum, and empty occupancy cells left without a read (the same lattice, so skipping
// changes no pixel).
import { compile, FULL_SCREEN_VERTEX } from './mesh.js';

const VERTEX = FULL_SCREEN_VERTEX;

const FRAGMENT = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler3D;
precision highp usampler3D;
uniform sampler3D grid;
uniform usampler3D occupancy;
uniform int n;           // voxels per axis
uniform int cells;       // occupancy cells per axis
uniform bool clamped;
uniform vec3 boxMin, boxMax;
uniform float stepM, minTransmittance;
uniform mat3 worldFromCam;
uniform vec3 centre;
uniform vec4 intrinsics;  // fx, fy, cx, cy of the canvas
uniform float canvasHeight;
out vec4 colour;

vec4 voxel(ivec3 i) {
  if (any(lessThan(i, ivec3(0))) || any(greaterThanEqual(i, ivec3(n)))) return vec4(0.0);
  return texelFetch(grid, i, 0);
}

vec4 trilinear(vec3 u) {
  vec3 g = u * float(n) - 0.5;
  if (clamped) g = clamp(g, vec3(0.0), vec3(float(n - 1)));
  ivec3 b = ivec3(floor(g));
  if (clamped) b = min(b, ivec3(max(n - 2, 0)));
  vec3 f = g - vec3(b);
  vec4 x00 = mix(voxel(b), voxel(b + ivec3(1, 0, 0)), f.x);
  vec4 x10 = mix(voxel(b + ivec3(0, 1, 0)), voxel(b + ivec3(1, 1, 0)), f.x);
  vec4 x01 = mix(voxel(b + ivec3(0, 0, 1)), voxel(b + ivec3(1, 0, 1)), f.x);
  vec4 x11 = mix(voxel(b + ivec3(0, 1, 1)), voxel(b + ivec3(1, 1, 1)), f.x);
  return mix(mix(x00, x10, f.y), mix(x01, x11, f.y), f.z);
}

void main() {
  vec2 pixel = vec2(gl_FragCoord.x - 0.5, canvasHeight - gl_FragCoord.y - 0.5);
  vec3 d = normalize(worldFromCam * vec3((pixel.x - intrinsics.z) / intrinsics.x,
                                         (pixel.y - intrinsics.w) / intrinsics.y, 1.0));
  vec3 o = centre;
  vec3 inv = 1.0 / d;
  vec3 t0 = (boxMin - o) * inv, t1 = (boxMax - o) * inv;
  vec3 tmin = min(t0, t1), tmax = max(t0, t1);
  float tNear = max(max(max(tmin.x, tmin.y), tmin.z), 0.0);
  float tFar = min(min(tmax.x, tmax.y), tmax.z);
  vec3 rgb = vec3(0.0);
  float transmittance = 1.0;
  vec3 extent = boxMax - boxMin;
  if (tFar > tNear) {
    int k = 0;
    for (int guard = 0; guard < 4096; ++guard) {
      float t = tNear + float(k) * stepM;
      if (t >= tFar) break;
      vec3 p = o + t * d;
      vec3 u = (p - boxMin) / extent;
      ivec3 cell = clamp(ivec3(floor(u * float(cells))), ivec3(0), ivec3(cells - 1));
      if (texelFetch(occupancy, cell, 0).r == 0u) {
        // Leave the empty cell: the first sample of the lattice past its far face.
        vec3 cellSize = extent / float(cells);
        vec3 face = vec3(cell) + step(vec3(0.0), d);
        vec3 exits = (boxMin + face * cellSize - p) * inv;
        float exitT = t + max(min(min(exits.x, exits.y), exits.z), 0.0);
        k = max(k + 1, int(ceil((exitT - tNear) / stepM + 1e-6)));
        continue;
      }
      vec4 value = trilinear(u);
      float sigma = max(value.a, 0.0);
      float decay = exp(-sigma * stepM);
      rgb += transmittance * (1.0 - decay) * value.rgb;
      transmittance *= decay;
      if (transmittance < minTransmittance) break;
      ++k;
    }
  }
  colour = vec4(rgb.bgr, 1.0 - transmittance);  // the grid holds B, G, R
}`;

export class VolumeRenderer {
  constructor(gl) {
    this.gl = gl;
    this.program = compile(gl, VERTEX, FRAGMENT);
    this.grid = gl.createTexture();
    this.occupancy = gl.createTexture();
    this.vao = gl.createVertexArray();
    this.current = null;
  }

  upload(volume) {
    if (this.current === volume) return;
    const gl = this.gl, h = volume.header, n = h.grid, cells = Math.max(h.occupancy_cells, 1);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.bindTexture(gl.TEXTURE_3D, this.grid);
    gl.texImage3D(gl.TEXTURE_3D, 0, gl.RGBA32F, n, n, n, 0, gl.RGBA, gl.FLOAT, volume.rgba);
    for (const texture of [this.grid, this.occupancy]) {
      gl.bindTexture(gl.TEXTURE_3D, texture);
      gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      if (texture === this.occupancy)
        gl.texImage3D(gl.TEXTURE_3D, 0, gl.R8UI, cells, cells, cells, 0, gl.RED_INTEGER,
                      gl.UNSIGNED_BYTE, volume.occupancy);
    }
    this.current = volume;
  }

  draw(volume, camera, canvasHeight) {
    const gl = this.gl, h = volume.header, p = this.program;
    this.upload(volume);
    gl.useProgram(p);
    const u = (name) => gl.getUniformLocation(p, name);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_3D, this.grid);
    gl.uniform1i(u('grid'), 0);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_3D, this.occupancy);
    gl.uniform1i(u('occupancy'), 1);
    gl.uniform1i(u('n'), h.grid);
    gl.uniform1i(u('cells'), Math.max(h.occupancy_cells, 1));
    gl.uniform1i(u('clamped'), h.clamped ? 1 : 0);
    gl.uniform3fv(u('boxMin'), h.box_min);
    gl.uniform3fv(u('boxMax'), h.box_max);
    gl.uniform1f(u('stepM'), h.step_m);
    gl.uniform1f(u('minTransmittance'), h.min_transmittance);
    const R = camera.R;  // cam_from_world; its transpose, column-major, is R itself row-major
    gl.uniformMatrix3fv(u('worldFromCam'), false,
                        new Float32Array([R[0][0], R[0][1], R[0][2], R[1][0], R[1][1], R[1][2],
                                          R[2][0], R[2][1], R[2][2]]));
    const c = [0, 1, 2].map((j) => -(R[0][j] * camera.t[0] + R[1][j] * camera.t[1] +
                                     R[2][j] * camera.t[2]));
    gl.uniform3fv(u('centre'), c);
    gl.uniform4f(u('intrinsics'), camera.fx, camera.fy, camera.cx, camera.cy);
    gl.uniform1f(u('canvasHeight'), canvasHeight);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);  // premultiplied colour over what is drawn
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);
  }
}
