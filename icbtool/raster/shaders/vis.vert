// Visibility pass: positions and the face id. icbtool.raster prepends "#version 330 core".
layout(location = 0) in vec3 a_position;
layout(location = 1) in float a_face;  // face index + 1 of the face whose last vertex this is
uniform mat4 u_clip_from_world;  // GL projection * GL view
invariant gl_Position;  // an optional depth pre-pass (depth.vert) must agree exactly
flat out float v_face;  // flat: taken from the provoking (last) vertex, i.e. this face's own

void main() {
    v_face = a_face;
    gl_Position = u_clip_from_world * vec4(a_position, 1.0);
}
