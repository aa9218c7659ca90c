// Background of the WRT-buffer before the geometry: every target 0, DL = the sky radiance along
// the pixel's ray with coverage 0 (icbtool.scene.Sky.radiance; icbtool/raster resolve.frag).
precision highp float;
uniform float u_height;
uniform vec4 u_intrinsics;      // fx, fy, cx, cy
uniform mat3 u_world_from_cam;  // OpenCV axes -> world
uniform int u_sky;              // 0 none, 1 uniform, 2 gradient
uniform vec3 u_zenith;
uniform vec3 u_horizon;
uniform vec3 u_ground;
uniform vec3 u_up;
layout(location = 0) out vec4 o_albedo;
layout(location = 1) out vec4 o_normal;
layout(location = 2) out vec4 o_pos;
layout(location = 3) out vec4 o_dl;

void main() {
    o_albedo = vec4(0.0);
    o_normal = vec4(0.0);
    o_pos = vec4(0.0);
    vec3 sky = vec3(0.0);
    if (u_sky == 1) {
        sky = u_zenith;
    } else if (u_sky == 2) {
        float u = gl_FragCoord.x;
        float v = u_height - gl_FragCoord.y;
        vec3 d = normalize(u_world_from_cam * vec3((u - u_intrinsics.z) / u_intrinsics.x,
                                                   (v - u_intrinsics.w) / u_intrinsics.y, 1.0));
        float c = dot(d, u_up);
        float w = sqrt(clamp(c, 0.0, 1.0));
        sky = c >= 0.0 ? (1.0 - w) * u_horizon + w * u_zenith : u_ground;
    }
    o_dl = vec4(sky, 0.0);
}
