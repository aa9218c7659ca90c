// To the canvas: one of final / DL / GI / holes, through icbtool's display transform (exposure,
// clip to [0, 1], sRGB encode; icbtool.imageio.to_display). Holes: icbtool.warp.HOLE_COLOURS
// over the dimmed frame, filled pixels marked like their cause.
precision highp float;
precision highp sampler2D;
in vec2 v_xy;
uniform sampler2D u_final;   // (final rgb, GI code before filling)
uniform sampler2D u_dl;
uniform sampler2D u_gi;      // filled GI (rgb, code)
uniform sampler2D u_holes;   // combined GI before filling (rgb, code)
uniform int u_mode;          // 0 final, 1 DL, 2 GI, 3 holes
uniform float u_exposure;
out vec4 o_color;

vec3 srgb(vec3 x) {
    x = clamp(x, 0.0, 1.0);
    return mix(12.92 * x, 1.055 * pow(x, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, x));
}

void main() {
    vec3 c;
    if (u_mode == 1) {
        c = texture(u_dl, v_xy).rgb;
    } else if (u_mode == 2) {
        vec4 g = texture(u_gi, v_xy);
        c = g.a > 0.0 ? g.rgb : vec3(0.0);
    } else {
        c = texture(u_final, v_xy).rgb;
    }
    c = srgb(c * u_exposure);
    if (u_mode == 3) {
        float code = texture(u_holes, v_xy).a;
        if (code == -1.0) c = vec3(255.0, 64.0, 64.0) / 255.0;
        else if (code == -2.0) c = vec3(255.0, 200.0, 0.0) / 255.0;
        else if (code == -3.0) c = vec3(40.0) / 255.0;
        else c *= 0.5;
    }
    o_color = vec4(c, 1.0);
}
