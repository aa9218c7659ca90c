// Background DL: the sky radiance along the primary ray (icbtool.scene.Sky.radiance).
// SKY_GRADIENT selects the gradient sky, else uniform. Alpha 0: background keeps mask 0.
uniform float u_height;
uniform vec4 u_intrinsics;        // fx, fy, cx, cy (icbtool pixel convention)
uniform mat3 u_world_from_cam;    // OpenCV camera axes -> world
uniform vec3 u_zenith;
uniform vec3 u_horizon;
uniform vec3 u_ground;
uniform vec3 u_up;

layout(location = 0) out vec4 o_dl;

void main() {
#ifdef SKY_GRADIENT
    // GL window origin is bottom-left; icbtool's v grows downwards.
    float u = gl_FragCoord.x;
    float v = u_height - gl_FragCoord.y;
    vec3 dc = vec3((u - u_intrinsics.z) / u_intrinsics.x, (v - u_intrinsics.w) / u_intrinsics.y, 1.0);
    vec3 d = normalize(u_world_from_cam * dc);
    float c = dot(d, u_up);
    float w = sqrt(clamp(c, 0.0, 1.0));
    vec3 sky = (1.0 - w) * u_horizon + w * u_zenith;
    o_dl = vec4(c >= 0.0 ? sky : u_ground, 0.0);
#else
    o_dl = vec4(u_zenith, 0.0);
#endif
}
