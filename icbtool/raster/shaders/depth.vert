// Depth-only pass (shadow maps and the camera depth pre-pass).
layout(location = 0) in vec3 a_position;
uniform mat4 u_clip_from_world;
invariant gl_Position;  // the depth pre-pass and the shading pass must agree exactly

void main() {
    gl_Position = u_clip_from_world * vec4(a_position, 1.0);
}
