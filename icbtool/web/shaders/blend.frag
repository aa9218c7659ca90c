// The final frame: DL + w * GI (rgb), alpha = the GI code (holes view) - a float target that
// the tests read back.
precision highp float;
precision highp sampler2D;
uniform sampler2D u_dl;   // WRT-buffer direct light
uniform sampler2D u_gi;   // filled GI (rgb, code)
uniform float u_gi_weight;
out vec4 o_final;

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 g = texelFetch(u_gi, px, 0);
    vec3 gi = g.a > 0.0 ? g.rgb : vec3(0.0);
    o_final = vec4(texelFetch(u_dl, px, 0).rgb + u_gi_weight * gi, g.a);
}
