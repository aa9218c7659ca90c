// Shadow-map pass: depth only (render.js prepends "#version 300 es").
precision highp float;
in vec3 position;
uniform mat4 u_clip_from_world;
invariant gl_Position;

void main() {
    gl_Position = u_clip_from_world * vec4(position, 1.0);
}
