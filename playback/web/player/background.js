// Draws what a stream's source sees behind the subject through a capture camera (a Neural
// Volume's learned background, or the take's clean plate; manifest "backgrounds", one PNG per
// camera in its pinhole core), so that looking through that camera shows the picture holocap
// scores against the camera's image: the subject composited over it as the native render is.
// The PNG's texels are copied as they are (no colour conversion, no premultiplication),
// sampled bilinearly where the canvas is not the camera's size.
import { compile, FULL_SCREEN_VERTEX } from './mesh.js';

const VERTEX = FULL_SCREEN_VERTEX;

const FRAGMENT = `#version 300 es
precision highp float;
uniform sampler2D image;
uniform vec2 size;         // the camera's width and height in pixels
uniform float scale;       // canvas pixels per camera pixel
uniform float top;         // the canvas row where the camera's picture starts
uniform float canvasHeight;
out vec4 colour;
void main() {
  vec2 pixel = vec2(gl_FragCoord.x - 0.5, canvasHeight - gl_FragCoord.y - 0.5 - top);
  vec2 uv = (pixel + 0.5) / scale / size;
  if (uv.y < 0.0 || uv.y > 1.0) discard;
  colour = vec4(texture(image, uv).rgb, 1.0);
}`;

export class BackgroundRenderer {
  constructor(gl, base) {
    this.gl = gl;
    this.base = base;
    this.program = compile(gl, VERTEX, FRAGMENT);
    this.vao = gl.createVertexArray();
    this.images = new Map();  // url -> {state: 'loading' | 'ready' | 'failed', texture}
  }

  // The texture of `url` once loaded (null until then, or when it failed).
  texture(url) {
    let entry = this.images.get(url);
    if (!entry) {
      entry = { state: 'loading', texture: null };
      this.images.set(url, entry);
      fetch(new URL(url, this.base))
        .then((r) => {
          if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
          return r.blob();
        })
        .then((blob) => createImageBitmap(blob, { colorSpaceConversion: 'none', premultiplyAlpha: 'none' }))
        .then((bitmap) => {
          const gl = this.gl;
          entry.texture = gl.createTexture();
          gl.bindTexture(gl.TEXTURE_2D, entry.texture);
          gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
          gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
          gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
          gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, bitmap);
          for (const [name, value] of [[gl.TEXTURE_MIN_FILTER, gl.LINEAR], [gl.TEXTURE_MAG_FILTER, gl.LINEAR],
                                       [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]])
            gl.texParameteri(gl.TEXTURE_2D, name, value);
          entry.state = 'ready';
        })
        .catch(() => { entry.state = 'failed'; });
    }
    return entry;
  }

  // Draws the background of capture camera `c` (the manifest's) on a W x H canvas, placed as
  // math.js captureCamera places the camera's picture. Returns 'ready', 'loading' or 'failed'.
  draw(url, c, W, H) {
    const entry = this.texture(url);
    if (entry.state !== 'ready') return entry.state;
    const gl = this.gl, p = this.program, s = W / c.width;
    gl.useProgram(p);
    const u = (name) => gl.getUniformLocation(p, name);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, entry.texture);
    gl.uniform1i(u('image'), 0);
    gl.uniform2f(u('size'), c.width, c.height);
    gl.uniform1f(u('scale'), s);
    gl.uniform1f(u('top'), (H - c.height * s) / 2);
    gl.uniform1f(u('canvasHeight'), H);
    gl.disable(gl.DEPTH_TEST);
    gl.disable(gl.BLEND);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindVertexArray(null);
    return 'ready';
  }
}
