// WRT-buffer pass (G-buffers + direct light), vertex stage. icbtool/web/src/render.js prepends
// "#version 300 es" (three.js GLSL3) and the #defines of gbuffer.frag.
precision highp float;
in vec3 position;        // world, per face corner (the level is de-indexed)
in vec3 normal;          // shading normal
in vec2 uv;              // (0, 0) = image bottom-left (docs/lpm.md)
in vec3 face_normal;     // the face's geometric normal (same on its 3 corners)
in float material;       // index into u_materials
uniform mat4 u_clip_from_world;
invariant gl_Position;
out vec3 v_pos;
out vec3 v_n;
out vec2 v_uv;
flat out vec3 v_ng;
flat out int v_mat;

void main() {
    v_pos = position;
    v_n = normal;
    v_uv = uv;
    v_ng = face_normal;
    v_mat = int(material + 0.5);
    gl_Position = u_clip_from_world * vec4(position, 1.0);
}
