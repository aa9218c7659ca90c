// Scene pass: G-buffer + direct lighting (DL) into float MRT targets.
// icbtool.raster prepends "#version 330 core" and #defines:
//   LOC_<BUFFER> n  output location of each requested buffer (DL, ALBEDO, NW, NV, DEPTH, POS, MASK)
//   HAS_TEX         some material is textured (sampler2DArray, per-material layer)
//   N_DIR, N_POINT, N_SPOT, N_AREA   number of lights of each kind (0 = code compiled out)
//   SHADOWS         shadow lookups on;  AREA_K  k x k shadow samples per area light
// Every target gets alpha = 1 (cleared to 0: alpha is the coverage mask).
const float PI = 3.14159265358979;

in vec3 v_position;
in vec3 v_normal;
#ifdef HAS_TEX
in vec2 v_uv;
uniform sampler2DArray u_textures;
#endif

uniform samplerBuffer u_faces;      // per face: (geometric normal xyz, material index)
uniform int u_prim_base;            // index of this draw's first face in u_faces
uniform samplerBuffer u_materials;  // per material: (albedo rgb, texture layer or -1), (emission rgb, 0)
uniform vec3 u_cam_pos;             // camera centre, world
uniform vec3 u_cam_forward;         // +z camera axis, world
uniform mat3 u_cam_from_world;      // rotation world -> OpenCV camera axes

#ifdef LOC_DL
layout(location = LOC_DL) out vec4 o_dl;
#endif
#ifdef LOC_ALBEDO
layout(location = LOC_ALBEDO) out vec4 o_albedo;
#endif
#ifdef LOC_NW
layout(location = LOC_NW) out vec4 o_nw;
#endif
#ifdef LOC_NV
layout(location = LOC_NV) out vec4 o_nv;
#endif
#ifdef LOC_DEPTH
layout(location = LOC_DEPTH) out vec4 o_depth;
#endif
#ifdef LOC_POS
layout(location = LOC_POS) out vec4 o_pos;
#endif
#ifdef LOC_MASK
layout(location = LOC_MASK) out vec4 o_mask;
#endif

#ifdef LOC_DL
#ifdef SHADOWS
#if (N_DIR + N_POINT + N_SPOT) > 0
uniform sampler2DArrayShadow u_shadow;       // sharp shadow maps (sun, point cube faces, spot)
uniform mat4 u_shadow_mat[N_DIR + 6 * N_POINT + N_SPOT];    // shadow clip from world
uniform float u_shadow_texel[N_DIR + 6 * N_POINT + N_SPOT]; // texel size at light-view depth 1
#endif
#if N_AREA > 0
uniform sampler2DArrayShadow u_area_shadow;  // one map per area-light sample point
uniform mat4 u_area_mat[N_AREA * AREA_K * AREA_K];
uniform float u_area_texel[N_AREA * AREA_K * AREA_K];
#endif
uniform float u_normal_offset;  // in texels

// 1 = lit, 0 = shadowed (bilinear PCF when the sampler filters linearly). Outside the map: lit.
// w0: the receiver's depth in the light view (1 for orthographic views), scales the texel size.
float shadow_lookup(sampler2DArrayShadow tex, mat4 m, float texel, int layer, vec3 p, vec3 ng,
                    float cos_l, float w0) {
    float sin_l = sqrt(max(0.0, 1.0 - cos_l * cos_l));
    vec3 q = p + ng * (u_normal_offset * texel * max(w0, 0.0) * sin_l);
    vec4 c = m * vec4(q, 1.0);
    if (c.w <= 0.0) return 1.0;
    vec3 ndc = c.xyz / c.w;
    if (any(greaterThan(abs(ndc), vec3(1.0)))) return 1.0;
    vec3 s = ndc * 0.5 + 0.5;
    return texture(tex, vec4(s.xy, float(layer), s.z));
}
#endif

#if N_DIR > 0
uniform vec3 u_dir_dir[N_DIR];   // direction the light travels
uniform vec3 u_dir_E[N_DIR];     // irradiance, W/m^2
#endif
#if N_POINT > 0
uniform vec3 u_point_pos[N_POINT];
uniform vec3 u_point_I[N_POINT]; // intensity, W/sr
#endif
#if N_SPOT > 0
uniform vec3 u_spot_pos[N_SPOT];
uniform vec3 u_spot_dir[N_SPOT];
uniform vec3 u_spot_I[N_SPOT];
uniform vec2 u_spot_cos[N_SPOT]; // cos(inner), cos(outer)
#endif
#if N_AREA > 0
uniform vec3 u_area_corner[N_AREA];
uniform vec3 u_area_eu[N_AREA];
uniform vec3 u_area_ev[N_AREA];
uniform vec3 u_area_L[N_AREA];   // radiance

// Irradiance / radiance of the polygon (corner, eu, ev) at p with normal n: Lambert's formula
// 1/2 sum_i Theta_i (n . gamma_i), after clipping the polygon to the upper hemisphere of n.
float polygon_irradiance(vec3 corner, vec3 eu, vec3 ev, vec3 p, vec3 n) {
    vec3 q[4] = vec3[4](corner - p, corner + eu - p, corner + eu + ev - p, corner + ev - p);
    vec3 v[5];
    int m = 0;
    for (int i = 0; i < 4; ++i) {  // Sutherland-Hodgman against the plane dot(n, x) = 0
        vec3 a = q[i];
        vec3 b = q[(i + 1) % 4];
        float da = dot(n, a);
        float db = dot(n, b);
        if (da > 0.0) { v[m] = a; m++; }
        if ((da > 0.0) != (db > 0.0)) { v[m] = a + (b - a) * (da / (da - db)); m++; }
    }
    if (m < 3) return 0.0;
    float sum = 0.0;
    for (int i = 0; i < 5; ++i) {
        if (i >= m) break;
        vec3 a = normalize(v[i]);
        vec3 b = normalize(v[(i + 1) % m]);
        vec3 c = cross(a, b);
        float lc = length(c);
        if (lc > 1e-12) sum += atan(lc, dot(a, b)) * dot(n, c / lc);
    }
    return 0.5 * abs(sum);
}
#endif

float spot_falloff(float c, vec2 cs) {
    float x = clamp((c - cs.y) / (cs.x - cs.y), 0.0, 1.0);
    return x * x * (3.0 - 2.0 * x);
}
#endif  // LOC_DL

void main() {
    vec4 face = texelFetch(u_faces, gl_PrimitiveID + u_prim_base);
    int mat = int(face.w + 0.5);
    vec4 m0 = texelFetch(u_materials, 2 * mat);
    vec3 albedo = m0.rgb;
#ifdef HAS_TEX
    if (m0.w >= 0.0) albedo *= texture(u_textures, vec3(v_uv, m0.w)).rgb;
#endif
    // Two-sided surfaces: seen from behind, both normals are flipped to face the camera.
    vec3 ng = gl_FrontFacing ? face.xyz : -face.xyz;
    vec3 ns = normalize(v_normal);
    if (!gl_FrontFacing) ns = -ns;
    vec3 p = v_position;

#ifdef LOC_DL
    vec3 dl = gl_FrontFacing ? texelFetch(u_materials, 2 * mat + 1).rgb : vec3(0.0);
    vec3 brdf = albedo / PI;
#if N_DIR > 0
    for (int i = 0; i < N_DIR; ++i) {
        vec3 l = -u_dir_dir[i];
        float cg = dot(ng, l);
        if (cg <= 0.0) continue;
        float vis = 1.0;
#ifdef SHADOWS
        vis = shadow_lookup(u_shadow, u_shadow_mat[i], u_shadow_texel[i], i, p, ng, cg, 1.0);
#endif
        dl += brdf * u_dir_E[i] * max(dot(ns, l), 0.0) * vis;
    }
#endif
#if N_POINT > 0
    for (int i = 0; i < N_POINT; ++i) {
        vec3 d = u_point_pos[i] - p;
        float r2 = dot(d, d);
        vec3 l = d * inversesqrt(r2);
        float cg = dot(ng, l);
        if (cg <= 0.0) continue;
        float vis = 1.0;
#ifdef SHADOWS
        vec3 a = -d;  // light -> point selects the cube face: +x -x +y -y +z -z
        vec3 aa = abs(a);
        int f = (aa.x >= aa.y && aa.x >= aa.z) ? (a.x > 0.0 ? 0 : 1)
              : ((aa.y >= aa.z) ? (a.y > 0.0 ? 2 : 3) : (a.z > 0.0 ? 4 : 5));
        int layer = N_DIR + 6 * i + f;
        vis = shadow_lookup(u_shadow, u_shadow_mat[layer], u_shadow_texel[layer], layer, p, ng, cg,
                            (u_shadow_mat[layer] * vec4(p, 1.0)).w);
#endif
        dl += brdf * u_point_I[i] / r2 * max(dot(ns, l), 0.0) * vis;
    }
#endif
#if N_SPOT > 0
    for (int i = 0; i < N_SPOT; ++i) {
        vec3 d = u_spot_pos[i] - p;
        float r2 = dot(d, d);
        vec3 l = d * inversesqrt(r2);
        float cg = dot(ng, l);
        float fall = spot_falloff(dot(-l, u_spot_dir[i]), u_spot_cos[i]);
        if (cg <= 0.0 || fall <= 0.0) continue;
        float vis = 1.0;
#ifdef SHADOWS
        int layer = N_DIR + 6 * N_POINT + i;
        vis = shadow_lookup(u_shadow, u_shadow_mat[layer], u_shadow_texel[layer], layer, p, ng, cg,
                            (u_shadow_mat[layer] * vec4(p, 1.0)).w);
#endif
        dl += brdf * u_spot_I[i] * fall / r2 * max(dot(ns, l), 0.0) * vis;
    }
#endif
#if N_AREA > 0
    for (int i = 0; i < N_AREA; ++i) {
        vec3 nl = normalize(cross(u_area_eu[i], u_area_ev[i]));
        vec3 c = u_area_corner[i] + 0.5 * (u_area_eu[i] + u_area_ev[i]);
        if (dot(p - u_area_corner[i], nl) <= 0.0) continue;  // behind the emitter (one-sided)
        float e = polygon_irradiance(u_area_corner[i], u_area_eu[i], u_area_ev[i], p, ns);
        if (e <= 0.0) continue;
        float vis = 1.0;
#ifdef SHADOWS
        // Visibility fraction: shadow tests towards k x k stratified points on the light,
        // weighted by their unshadowed contribution cos * cos' / r^2.
        float wsum = 0.0;
        float vsum = 0.0;
        float w0 = dot(p - u_area_corner[i], nl);  // depth in every sample's view (axis nl)
        for (int sj = 0; sj < AREA_K; ++sj) {
            for (int si = 0; si < AREA_K; ++si) {
                vec3 s = u_area_corner[i] + (float(si) + 0.5) / float(AREA_K) * u_area_eu[i]
                       + (float(sj) + 0.5) / float(AREA_K) * u_area_ev[i];
                vec3 d = s - p;
                float r2 = dot(d, d);
                vec3 l = d * inversesqrt(r2);
                float w = max(dot(ns, l), 0.0) * max(-dot(nl, l), 0.0) / r2;
                if (w <= 0.0) continue;
                int layer = (i * AREA_K + sj) * AREA_K + si;
                float cg = max(dot(ng, l), 0.0);
                wsum += w;
                vsum += w * shadow_lookup(u_area_shadow, u_area_mat[layer], u_area_texel[layer],
                                          layer, p, ng, cg, w0);
            }
        }
        vis = wsum > 0.0 ? vsum / wsum : 1.0;
#endif
        dl += brdf * u_area_L[i] * e * vis;
    }
#endif
    o_dl = vec4(dl, 1.0);
#endif  // LOC_DL

#ifdef LOC_ALBEDO
    o_albedo = vec4(albedo, 1.0);
#endif
#ifdef LOC_NW
    o_nw = vec4(ns, 1.0);
#endif
#ifdef LOC_NV
    o_nv = vec4(u_cam_from_world * ns, 1.0);
#endif
#ifdef LOC_DEPTH
    o_depth = vec4(dot(p - u_cam_pos, u_cam_forward), 0.0, 0.0, 1.0);
#endif
#ifdef LOC_POS
    o_pos = vec4(p, 1.0);
#endif
#ifdef LOC_MASK
    o_mask = vec4(1.0);
#endif
}
