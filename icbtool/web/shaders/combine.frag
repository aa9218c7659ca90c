// Combine the warps of the current and the previous reference (icbtool.warp.combine): per
// pixel the valid one with the larger score; a hole only where both are holes, "outside" only
// if outside both.
precision highp float;
precision highp sampler2D;
uniform sampler2D u_a;  // current reference (wins ties)
uniform sampler2D u_b;  // previous reference
out vec4 o_gi;

void main() {
    vec4 a = texelFetch(u_a, ivec2(gl_FragCoord.xy), 0);
    vec4 b = texelFetch(u_b, ivec2(gl_FragCoord.xy), 0);
    if (a.a > 0.0 || b.a > 0.0) {
        o_gi = b.a > a.a ? b : a;
    } else if (a.a == -3.0) {
        o_gi = a;
    } else {
        o_gi = vec4(0.0, 0.0, 0.0, (a.a == -1.0 && b.a == -1.0) ? -1.0 : -2.0);
    }
}
