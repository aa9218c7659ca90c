// Scene pass: world position, shading normal and uv per vertex. icbtool.raster prepends
// "#version 330 core" and the #defines.
layout(location = 0) in vec3 a_position;
layout(location = 1) in vec3 a_normal;
#ifdef HAS_TEX
layout(location = 2) in vec2 a_uv;
out vec2 v_uv;
#endif

uniform mat4 u_clip_from_world;  // GL projection * GL view
invariant gl_Position;  // the depth pre-pass and the shading pass must agree exactly

out vec3 v_position;
out vec3 v_normal;

void main() {
    v_position = a_position;
    v_normal = a_normal;
#ifdef HAS_TEX
    v_uv = a_uv;
#endif
    gl_Position = u_clip_from_world * vec4(a_position, 1.0);
}
