// Visibility pass: positions only. icbtool.raster prepends "#version 330 core".
layout(location = 0) in vec3 a_position;
uniform mat4 u_clip_from_world;  // GL projection * GL view
invariant gl_Position;  // an optional depth pre-pass (depth.vert) must agree exactly

void main() {
    gl_Position = u_clip_from_world * vec4(a_position, 1.0);
}
