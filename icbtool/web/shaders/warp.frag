// Backward 3D warp of a reference GI map to the client camera (icbtool.warp.backward): every
// client pixel's world position (WRT-buffer) is projected into the reference camera and the
// reference GI is sampled with 4 bilinear taps, each tap kept only if the reference saw the same
// surface there (|z / z_tap - 1| <= u_rel_tol: a per-tap depth test, without icbtool's slope
// extrapolation). Output (rgb = GI, a = code): code in (1, 2] = 1 + weight * min(density, 1)
// (combine.frag keeps the larger), -1 outside the reference frustum, -2 disoccluded, -3 no
// geometry at the client pixel.
precision highp float;
precision highp sampler2D;
in vec2 v_xy;
uniform sampler2D u_pos;          // client WRT-buffer: (world position, view depth; 0 = background)
uniform sampler2D u_ref_gi;       // reference GI (row 0 = the image's top row)
uniform sampler2D u_ref_depth;    // reference view depth, 0 where its mask is 0
uniform mat4 u_ref_from_world;    // reference camera (OpenCV axes) from world
uniform vec4 u_ref_K;             // fx, fy, cx, cy of the reference
uniform vec4 u_dst_K;             // fx, fy, cx, cy of the client
uniform float u_rel_tol;
uniform float u_min_weight;
out vec4 o_gi;

void main() {
    vec4 pw = texelFetch(u_pos, ivec2(gl_FragCoord.xy), 0);
    if (pw.w <= 0.0) { o_gi = vec4(0.0, 0.0, 0.0, -3.0); return; }
    vec3 q = (u_ref_from_world * vec4(pw.xyz, 1.0)).xyz;
    ivec2 size = textureSize(u_ref_gi, 0);
    vec2 ws = vec2(size);
    if (q.z <= 1e-6) { o_gi = vec4(0.0, 0.0, 0.0, -1.0); return; }
    vec2 uv = vec2(u_ref_K.x * q.x / q.z + u_ref_K.z, u_ref_K.y * q.y / q.z + u_ref_K.w);
    if (any(lessThan(uv, vec2(0.0))) || any(greaterThan(uv, ws))) {
        o_gi = vec4(0.0, 0.0, 0.0, -1.0);
        return;
    }
    vec2 x = clamp(uv - 0.5, vec2(-0.5), ws - 0.5);
    vec2 x0 = floor(x);
    vec2 f = x - x0;
    vec3 acc = vec3(0.0);
    float wsum = 0.0;
    for (int k = 0; k < 4; ++k) {
        ivec2 o = ivec2(k & 1, k >> 1);
        ivec2 t = clamp(ivec2(x0) + o, ivec2(0), size - 1);
        float w = (o.x == 1 ? f.x : 1.0 - f.x) * (o.y == 1 ? f.y : 1.0 - f.y);
        float zt = texelFetch(u_ref_depth, t, 0).r;
        if (w <= 0.0 || !(zt > 0.0) || abs(q.z / zt - 1.0) > u_rel_tol) continue;
        acc += w * texelFetch(u_ref_gi, t, 0).rgb;
        wsum += w;
    }
    if (wsum <= u_min_weight) { o_gi = vec4(0.0, 0.0, 0.0, -2.0); return; }
    // reference pixels per client pixel at this point
    float density = (u_ref_K.x * u_ref_K.y / (q.z * q.z)) / (u_dst_K.x * u_dst_K.y / (pw.w * pw.w));
    o_gi = vec4(acc / wsum, 1.0 + wsum * min(density, 1.0));
}
