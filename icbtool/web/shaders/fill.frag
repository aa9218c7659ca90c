// One step of hole filling (icbtool.warp.inpaint, background-aware): a hole pixel that has
// geometry takes the mean of its known 3x3 neighbours, leaving out neighbours more than
// u_rel_gap nearer than it (the occluding foreground). Filled pixels get code 0.5 (known for the
// next step); render.js repeats the step until every hole is filled or a step limit is reached.
precision highp float;
precision highp sampler2D;
uniform sampler2D u_gi;   // (GI, code) as warp.frag / combine.frag write it
uniform sampler2D u_pos;  // client WRT-buffer (position, view depth)
uniform float u_rel_gap;
out vec4 o_gi;

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 c = texelFetch(u_gi, px, 0);
    if (c.a > 0.0 || c.a == -3.0) { o_gi = c; return; }
    ivec2 size = textureSize(u_gi, 0);
    float z = texelFetch(u_pos, px, 0).w;
    vec3 acc = vec3(0.0);
    float n = 0.0;
    for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
            ivec2 q = px + ivec2(dx, dy);
            if ((dx == 0 && dy == 0) || any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
            vec4 s = texelFetch(u_gi, q, 0);
            if (s.a <= 0.0) continue;
            float zq = texelFetch(u_pos, q, 0).w;
            if (zq < (1.0 - u_rel_gap) * z) continue;
            float w = (dx == 0 || dy == 0) ? 1.0 : 0.7071;
            acc += w * s.rgb;
            n += w;
        }
    }
    o_gi = n > 0.0 ? vec4(acc / n, 0.5) : c;
}
