// WRT-buffer pass, fragment stage: albedo, world normal, world position + view depth and direct
// light into 4 float targets (multiple render targets), with the light model and shadows of
// icbtool/raster/shaders/resolve.frag (sun, point, spot, area lights; shadow maps with bilinear
// PCF, slope-scaled bias in the shadow pass, normal offset at lookup; area lights: Lambert's
// polygon formula for the unshadowed irradiance, k x k shadow samples for the visibility with a
// receiver offset along the ray, penumbra pixels shaded again at AREA_SUB x AREA_SUB points).
// Differences: the shadow maps live in two depth atlases (one tile per view) instead of texture
// arrays; a penumbra's sub-pixel points extrapolate the position and normal with screen-space
// derivatives (the resolve pass intersects their rays with the face's plane). render.js
// #defines N_DIR, N_POINT, N_SPOT, N_AREA, AREA_K, AREA_SUB, SHADOWS, HAS_TEX.
precision highp float;
precision highp int;
precision highp sampler2D;
precision highp sampler2DShadow;
precision highp sampler2DArray;
const float PI = 3.14159265358979;

in vec3 v_pos;
in vec3 v_n;
in vec2 v_uv;
flat in vec3 v_ng;
flat in int v_mat;
uniform sampler2D u_materials;      // per material (x = 0: albedo rgb, texture layer or -1; x = 1: emission)
uniform vec3 u_cam_pos;
uniform vec3 u_cam_forward;
#ifdef HAS_TEX
uniform sampler2DArray u_textures;  // sRGB8 layers, mipmapped
#endif
layout(location = 0) out vec4 o_albedo;
layout(location = 1) out vec4 o_normal;
layout(location = 2) out vec4 o_pos;
layout(location = 3) out vec4 o_dl;

#ifdef SHADOWS
// per view (row): texels 0-3 the columns of its shadow clip_from_world, texel 4 (sample position
// xyz for area samples, texel size at light-view depth 1)
uniform sampler2D u_views;
uniform float u_normal_offset;      // in texels
#if (N_DIR + N_POINT + N_SPOT) > 0
uniform sampler2DShadow u_sharp;    // atlas of the sharp maps
uniform vec2 u_sharp_grid;          // (tiles per side, tile texels)
#endif
#if N_AREA > 0
uniform sampler2DShadow u_area;     // atlas of the area-sample maps
uniform vec2 u_area_grid;
uniform int u_area_view0;           // row of the first area sample in u_views
#endif

mat4 view_matrix(int row) {
    return mat4(texelFetch(u_views, ivec2(0, row), 0), texelFetch(u_views, ivec2(1, row), 0),
                texelFetch(u_views, ivec2(2, row), 0), texelFetch(u_views, ivec2(3, row), 0));
}

// Depth-compared lookup of the receiver point q (world) in view `row` of an atlas; outside the
// view: lit. `tile`: index in the atlas.
float atlas_lookup(sampler2DShadow atlas, vec2 grid, int row, int tile, vec3 q) {
    mat4 m = view_matrix(row);
    vec4 c = m * vec4(q, 1.0);
    if (c.w <= 0.0) return 1.0;
    vec3 ndc = c.xyz / c.w;
    if (any(greaterThan(abs(ndc), vec3(1.0)))) return 1.0;
    vec3 s = ndc * 0.5 + 0.5;
    float half_texel = 0.5 / grid.y;
    vec2 st = clamp(s.xy, vec2(half_texel), vec2(1.0 - half_texel));  // clamp to edge, per tile
    int cols = int(grid.x + 0.5);
    vec2 uv = (vec2(float(tile % cols), float(tile / cols)) + st) / grid.x;
    return texture(atlas, vec3(uv, s.z));
}

// 1 = lit, 0 = shadowed: the receiver offset along its geometric normal (sharp lights).
float shadow_lookup(sampler2DShadow atlas, vec2 grid, int row, int tile, vec3 p, vec3 ng,
                    float cos_l, float w0) {
    float texel = texelFetch(u_views, ivec2(4, row), 0).w;
    float sin_l = sqrt(max(0.0, 1.0 - cos_l * cos_l));
    return atlas_lookup(atlas, grid, row, tile,
                        p + ng * (u_normal_offset * texel * max(w0, 0.0) * sin_l));
}

#if N_AREA > 0
uniform float u_area_offset;        // in texels
// An area-light sample's visibility: the receiver moves towards the sample (along l, on its ray).
float area_shadow_lookup(int row, int tile, vec3 p, vec3 l, float cos_l, float w0) {
    float texel = texelFetch(u_views, ivec2(4, row), 0).w;
    float sin_l = sqrt(max(0.0, 1.0 - cos_l * cos_l));
    float k = u_area_offset * texel * max(w0, 0.0) * min(sin_l / max(cos_l, 1e-3), 8.0);
    return atlas_lookup(u_area, u_area_grid, row, tile, p + l * k);
}
#endif
#endif

#if N_DIR > 0
uniform vec3 u_dir_dir[N_DIR];
uniform vec3 u_dir_E[N_DIR];
#endif
#if N_POINT > 0
uniform vec3 u_point_pos[N_POINT];
uniform vec3 u_point_I[N_POINT];
#endif
#if N_SPOT > 0
uniform vec3 u_spot_pos[N_SPOT];
uniform vec3 u_spot_dir[N_SPOT];
uniform vec3 u_spot_I[N_SPOT];
uniform vec2 u_spot_cos[N_SPOT];
#endif
#if N_AREA > 0
uniform vec3 u_area_v[4 * N_AREA];
uniform vec3 u_area_L[N_AREA];

float polygon_irradiance(vec3 v0, vec3 v1, vec3 v2, vec3 v3, vec3 p, vec3 n) {
    vec3 q[4] = vec3[4](v0 - p, v1 - p, v2 - p, v3 - p);
    vec3 v[5];
    int m = 0;
    for (int i = 0; i < 4; ++i) {
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

// Shadowed irradiance / radiance of area light i at p (resolve.frag's area_irradiance).
float area_irradiance(int i, vec3 p, vec3 ns, vec3 ng, inout bool partial) {
    vec3 v0 = u_area_v[4 * i];
    vec3 v1 = u_area_v[4 * i + 1];
    vec3 v2 = u_area_v[4 * i + 2];
    vec3 v3 = u_area_v[4 * i + 3];
    vec3 nl = normalize(cross(v1 - v0, v3 - v0));
    float w0 = dot(p - v0, nl);
    if (w0 <= 0.0) return 0.0;
    float e = polygon_irradiance(v0, v1, v2, v3, p, ns);
    if (e <= 0.0) return 0.0;
#ifdef SHADOWS
    float wsum = 0.0;
    float vsum = 0.0;
    float vmin = 1.0;
    float vmax = 0.0;
    for (int j = 0; j < AREA_K * AREA_K; ++j) {
        int tile = i * AREA_K * AREA_K + j;
        int row = u_area_view0 + tile;
        vec3 s = texelFetch(u_views, ivec2(4, row), 0).xyz;
        vec3 d = s - p;
        float r2 = dot(d, d);
        vec3 l = d * inversesqrt(r2);
        float w = max(dot(ns, l), 0.0) * max(-dot(nl, l), 0.0) / r2;
        if (w <= 0.0) continue;
        float v = area_shadow_lookup(row, tile, p, l, max(dot(ng, l), 0.0), w0);
        wsum += w;
        vsum += w * v;
        vmin = min(vmin, v);
        vmax = max(vmax, v);
    }
    partial = partial || vmax - vmin > 1e-3;
    return wsum > 0.0 ? e * vsum / wsum : e;
#else
    return e;
#endif
}
#endif

float spot_falloff(float c, vec2 cs) {
    float x = clamp((c - cs.y) / (cs.x - cs.y), 0.0, 1.0);
    return x * x * (3.0 - 2.0 * x);
}

void main() {
    bool front = gl_FrontFacing;
    vec3 p = v_pos;
    vec3 ns = normalize(v_n);
    if (!front) ns = -ns;
    vec3 ng = front ? v_ng : -v_ng;
    vec4 m0 = texelFetch(u_materials, ivec2(0, v_mat), 0);
    vec3 albedo = m0.rgb;
#ifdef HAS_TEX
    if (m0.w >= 0.0) albedo *= texture(u_textures, vec3(v_uv.x, 1.0 - v_uv.y, m0.w)).rgb;
#endif
    vec3 dl = front ? texelFetch(u_materials, ivec2(1, v_mat), 0).rgb : vec3(0.0);
    vec3 brdf = albedo / PI;
#if N_DIR > 0
    for (int i = 0; i < N_DIR; ++i) {
        vec3 l = -u_dir_dir[i];
        float cg = dot(ng, l);
        if (cg <= 0.0) continue;
        float vis = 1.0;
#ifdef SHADOWS
        vis = shadow_lookup(u_sharp, u_sharp_grid, i, i, p, ng, cg, 1.0);
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
        vec3 a = -d;
        vec3 aa = abs(a);
        int f = (aa.x >= aa.y && aa.x >= aa.z) ? (a.x > 0.0 ? 0 : 1)
              : ((aa.y >= aa.z) ? (a.y > 0.0 ? 2 : 3) : (a.z > 0.0 ? 4 : 5));
        int layer = N_DIR + 6 * i + f;
        vis = shadow_lookup(u_sharp, u_sharp_grid, layer, layer, p, ng, cg,
                            (view_matrix(layer) * vec4(p, 1.0)).w);
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
        vis = shadow_lookup(u_sharp, u_sharp_grid, layer, layer, p, ng, cg,
                            (view_matrix(layer) * vec4(p, 1.0)).w);
#endif
        dl += brdf * u_spot_I[i] * fall / r2 * max(dot(ns, l), 0.0) * vis;
    }
#endif
#if N_AREA > 0
    bool partial = false;
    vec3 area = vec3(0.0);
    for (int i = 0; i < N_AREA; ++i) area += u_area_L[i] * area_irradiance(i, p, ns, ng, partial);
    // derivatives taken in uniform control flow, used only in penumbrae
    vec3 dpx = dFdx(v_pos);
    vec3 dpy = dFdy(v_pos);
    vec3 dnx = dFdx(v_n);
    vec3 dny = dFdy(v_n);
#if AREA_SUB > 1
    if (partial) {
        area = vec3(0.0);
        for (int sy = 0; sy < AREA_SUB; ++sy) {
            for (int sx = 0; sx < AREA_SUB; ++sx) {
                vec2 o = (vec2(sx, sy) + 0.5) / float(AREA_SUB) - 0.5;
                vec3 ps = p + o.x * dpx + o.y * dpy;
                vec3 nss = normalize(v_n + o.x * dnx + o.y * dny);
                if (!front) nss = -nss;
                bool unused = false;
                for (int i = 0; i < N_AREA; ++i)
                    area += u_area_L[i] * area_irradiance(i, ps, nss, ng, unused);
            }
        }
        area /= float(AREA_SUB * AREA_SUB);
    }
#endif
    dl += brdf * area;
#endif
    o_albedo = vec4(albedo, 1.0);
    o_normal = vec4(ns, 1.0);
    o_pos = vec4(p, dot(p - u_cam_pos, u_cam_forward));
    o_dl = vec4(dl, 1.0);
}
