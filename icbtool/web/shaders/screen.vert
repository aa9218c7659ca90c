// One triangle covering the screen (background, warp, combine, fill and display passes).
precision highp float;
out vec2 v_xy;  // [0, 1]^2, GL window axes

void main() {
    vec2 p = vec2((gl_VertexID == 1) ? 3.0 : -1.0, (gl_VertexID == 2) ? 3.0 : -1.0);
    v_xy = 0.5 * p + 0.5;
    gl_Position = vec4(p, 0.0, 1.0);
}
