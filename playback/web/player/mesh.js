// Draws a decoded mesh frame: positions per corner, the atlas sampled bilinearly (no mipmaps,
// clamped at its edges, as holocap's native renderer samples it), or per-corner colours.

function compile(gl, vertex, fragment) {
  const program = gl.createProgram();
  for (const [type, source] of [[gl.VERTEX_SHADER, vertex], [gl.FRAGMENT_SHADER, fragment]]) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS))
      throw new Error(`shader: ${gl.getShaderInfoLog(shader)}`);
    gl.attachShader(program, shader);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS))
    throw new Error(`program: ${gl.getProgramInfoLog(program)}`);
  return program;
}
// One triangle over the whole canvas (three vertices, no buffer): the vertex stage of the passes
// that shade every pixel (the volume's ray-march, a camera's background).
const FULL_SCREEN_VERTEX = `#version 300 es
void main() {
  vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

export { compile, FULL_SCREEN_VERTEX };

const VERTEX = `#version 300 es
in vec3 position;
in vec2 uv;
in vec3 color;
uniform mat4 view, projection;
out vec2 vUv;
out vec3 vColor;
void main() {
  vUv = uv;
  vColor = color;
  gl_Position = projection * view * vec4(position, 1.0);
}`;

const FRAGMENT = `#version 300 es
precision highp float;
in vec2 vUv;
in vec3 vColor;
uniform sampler2D atlas;
uniform bool textured;
out vec4 colour;
void main() {
  colour = vec4(textured ? texture(atlas, vUv).rgb : vColor, 1.0);
}`;

export class MeshRenderer {
  constructor(gl) {
    this.gl = gl;
    this.program = compile(gl, VERTEX, FRAGMENT);
    this.vao = gl.createVertexArray();
    this.buffers = { position: gl.createBuffer(), uv: gl.createBuffer(), color: gl.createBuffer() };
    this.texture = gl.createTexture();
    this.current = null;
  }

  upload(mesh) {
    if (this.current === mesh) return;
    const gl = this.gl;
    gl.bindVertexArray(this.vao);
    const attribute = (name, buffer, data, size, type, normalized) => {
      const location = gl.getAttribLocation(this.program, name);
      if (location < 0) return;
      if (!data) {
        gl.disableVertexAttribArray(location);
        return;
      }
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, size, type, normalized, 0, 0);
    };
    attribute('position', this.buffers.position, mesh.positions, 3, gl.FLOAT, false);
    attribute('uv', this.buffers.uv, mesh.uvs, 2, gl.FLOAT, false);
    attribute('color', this.buffers.color, mesh.colors, 3, gl.UNSIGNED_BYTE, true);
    gl.bindVertexArray(null);
    if (mesh.atlas) {
      gl.bindTexture(gl.TEXTURE_2D, this.texture);
      gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
      gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
      gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, mesh.atlas);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    }
    this.current = mesh;
  }

  draw(mesh, view, projection) {
    const gl = this.gl;
    this.upload(mesh);
    gl.useProgram(this.program);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.program, 'view'), false, view);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.program, 'projection'), false, projection);
    gl.uniform1i(gl.getUniformLocation(this.program, 'textured'), mesh.atlas ? 1 : 0);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.uniform1i(gl.getUniformLocation(this.program, 'atlas'), 0);
    gl.enable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3 * mesh.faces);
    gl.bindVertexArray(null);
  }
}
