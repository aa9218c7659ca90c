// Resolve pass of the deferred renderer: one full-screen triangle shades every pixel once from
// the visibility target (vis.frag: face id + facing). Per pixel: the camera ray through the pixel
// centre meets the face's plane (barycentrics), which interpolates the vertex position, shading
// normal and uv exactly like the rasterizer's perspective-correct interpolation; the texture
// footprint comes from the rays through the pixels of its 2x2 quad (the derivatives a GPU takes
// from neighbouring fragments), so textureGrad picks the same mip level.
// icbtool.raster prepends "#version 330 core" and #defines:
//   LOC_A n   albedo target:   (linear albedo rgb, 1)
//   LOC_N n   normal target:   (world shading normal facing the camera, 1)
//   LOC_P n   position target: (world position, view-space depth)
//   LOC_DL n  direct lighting: (DL rgb, 1); background: (sky radiance or 0, 0)
//   HAS_TEX   some material is textured (sampler2DArray, per-material layer)
//   N_DIR, N_POINT, N_SPOT, N_AREA   number of lights of each kind (0 = code compiled out)
//   SHADOWS         shadow lookups on;  AREA_K  k x k shadow samples per area light
//   AREA_SUB        s x s points per pixel for area light in penumbrae (1: the pixel centre)
//   SKY_UNIFORM / SKY_GRADIENT / SKY_ENVMAP   the scene's sky (none: background DL is 0)
//   GLOSSY          some material has a BSDF evaluated here (icbtool.raster.glossy's table)
//   GLOSSY_N        n x n quadrature points per area light for glossy materials
// Every output is 0 on background pixels except DL's colour; a non-zero alpha marks coverage.
const float PI = 3.14159265358979;

uniform sampler2D u_vis;            // R: +-(face + 1), 0 = background
uniform isamplerBuffer u_tris;      // per face: (vertex indices i0, i1, i2, material)
uniform samplerBuffer u_faces;      // per face: (geometric normal xyz, material index)
uniform samplerBuffer u_verts;      // per vertex: (position xyz, u), (shading normal xyz, v)
uniform samplerBuffer u_materials;  // per material: (albedo rgb, texture layer or -1), (emission rgb, 0)
uniform float u_height;
uniform vec4 u_intrinsics;          // fx, fy, cx, cy (icbtool pixel convention)
uniform mat3 u_world_from_cam;      // OpenCV camera axes -> world
uniform vec3 u_cam_pos;             // camera centre, world
uniform vec3 u_cam_forward;         // +z camera axis, world
#ifdef HAS_TEX
uniform sampler2DArray u_textures;
#endif

#ifdef LOC_A
layout(location = LOC_A) out vec4 o_albedo;
#endif
#ifdef LOC_N
layout(location = LOC_N) out vec4 o_normal;
#endif
#ifdef LOC_P
layout(location = LOC_P) out vec4 o_pos;
#endif
#ifdef LOC_DL
layout(location = LOC_DL) out vec4 o_dl;
#endif

// World direction (not normalised, camera z = 1) of the ray through this fragment's pixel centre
// moved by (dx, dy) pixels in GL window axes (x right, y up).
vec3 pixel_ray(float dx, float dy) {
    // GL window origin is bottom-left; icbtool's v grows downwards.
    float u = gl_FragCoord.x + dx;
    float v = u_height - (gl_FragCoord.y + dy);
    vec3 dc = vec3((u - u_intrinsics.z) / u_intrinsics.x, (v - u_intrinsics.w) / u_intrinsics.y, 1.0);
    return u_world_from_cam * dc;
}

// Barycentrics (b1, b2) of the point where the ray u_cam_pos + t d meets the plane of the
// triangle (v0, v0 + e1, v0 + e2) (Moller-Trumbore, without the inside test).
vec2 barycentrics(vec3 d, vec3 v0, vec3 e1, vec3 e2) {
    vec3 pv = cross(d, e2);
    float inv = 1.0 / dot(e1, pv);
    vec3 tv = u_cam_pos - v0;
    return vec2(dot(tv, pv), dot(d, cross(tv, e1))) * inv;
}

#if defined(SKY_UNIFORM) || defined(SKY_GRADIENT) || defined(SKY_ENVMAP)
#define HAS_SKY
#endif

#ifdef SKY_ENVMAP
uniform sampler2D u_env;            // lat-long map, RGB32F, H rows x (W + 1) (first column repeated)
uniform mat3 u_map_from_world;
uniform float u_env_scale;

// Radiance of the map along the world direction d: Mitsuba's envmap lookup (bilinear between
// texel centres at u = (i + 0.5) / W, v = j / (H - 1)), as icbtool.scene.Sky.radiance.
vec3 envmap_radiance(vec3 d) {
    vec3 l = u_map_from_world * normalize(d);
    ivec2 res = textureSize(u_env, 0);  // (W + 1, H)
    float u = atan(l.x, -l.z) * (0.5 / PI) - 0.5 / float(res.x - 1);
    u -= floor(u);
    float v = acos(clamp(l.y, -1.0, 1.0)) / PI;
    vec2 xy = vec2(u * float(res.x - 1), v * float(res.y - 1));
    ivec2 i = min(ivec2(xy), res - 2);
    vec2 f = xy - vec2(i);
    vec3 top = mix(texelFetch(u_env, i, 0).rgb, texelFetch(u_env, i + ivec2(1, 0), 0).rgb, f.x);
    vec3 bot = mix(texelFetch(u_env, i + ivec2(0, 1), 0).rgb,
                   texelFetch(u_env, i + ivec2(1, 1), 0).rgb, f.x);
    return u_env_scale * mix(top, bot, f.y);
}
#endif

#ifdef HAS_SKY
uniform vec3 u_zenith;
uniform vec3 u_horizon;
uniform vec3 u_ground;
uniform vec3 u_up;

// The sky radiance along this pixel's primary ray (icbtool.scene.Sky.radiance).
vec3 sky_radiance() {
#if defined(SKY_ENVMAP)
    return envmap_radiance(pixel_ray(0.0, 0.0));
#elif defined(SKY_GRADIENT)
    vec3 d = normalize(pixel_ray(0.0, 0.0));
    float c = dot(d, u_up);
    float w = sqrt(clamp(c, 0.0, 1.0));
    vec3 sky = (1.0 - w) * u_horizon + w * u_zenith;
    return c >= 0.0 ? sky : u_ground;
#else
    return u_zenith;
#endif
}
#endif

#ifdef LOC_DL
#ifdef GLOSSY
// Mitsuba 3's plastic, roughplastic, conductor and roughconductor, as icbtool.trace.bsdfs
// evaluates them (BSDF times cos(wo), local frame, wi towards the camera, wo towards the light;
// delta lobes give 0 here). Per material BSDF_ROWS texels of u_bsdf (icbtool.raster.glossy).
#define BSDF_ROWS 20
#define K_LAMBERT 0
#define K_PLASTIC 1
#define K_ROUGHPLASTIC 2
#define K_CONDUCTOR 3
#define K_ROUGHCONDUCTOR 4
uniform samplerBuffer u_bsdf;

struct Surf {
    int kind;    // K_*
    int base;    // first texel of the material's rows
    vec3 brdf;   // Lambert: albedo / pi
    vec3 ns;     // shading normal (facing the camera)
    mat3 local;  // world -> local shading frame (rows: s, t, n)
    vec3 wi;     // local direction towards the camera
    bool front;  // seen from the side the surface faces (one-sided BSDFs are black behind)
};

// Mitsuba's coordinate_system(n) (Duff et al. 2017): the frame the tracer builds from n.
mat3 frame_from(vec3 n) {
    float sgn = n.z >= 0.0 ? 1.0 : -1.0;
    float a = -1.0 / (sgn + n.z);
    float b = n.x * n.y * a;
    vec3 s = vec3(1.0 + sgn * n.x * n.x * a, sgn * b, -sgn * n.x);
    vec3 t = vec3(b, sgn + n.y * n.y * a, -n.y);
    return transpose(mat3(s, t, n));
}

// Unpolarised Fresnel reflectance of a dielectric interface seen from outside (cos_i >= 0).
float fresnel_dielectric(float ci, float eta) {
    if (eta == 1.0) return 0.0;
    float ct2 = 1.0 - (1.0 - ci * ci) / (eta * eta);
    if (ct2 <= 0.0 || ci <= 0.0) return 1.0;
    float ct = sqrt(ct2);
    float a_s = (ci - eta * ct) / (ci + eta * ct);
    float a_p = (ct - eta * ci) / (ct + eta * ci);
    return 0.5 * (a_s * a_s + a_p * a_p);
}

// Mitsuba's fresnel_conductor (complex IOR eta_r + i eta_i), one channel.
float fresnel_conductor(float ci, float er, float ei) {
    float c2 = ci * ci;
    float s2 = 1.0 - c2;
    float s4 = s2 * s2;
    float t1 = er * er - ei * ei - s2;
    float a2pb2 = sqrt(max(t1 * t1 + 4.0 * ei * ei * er * er, 0.0));
    float a = sqrt(max(0.5 * (a2pb2 + t1), 0.0));
    float term1 = a2pb2 + c2;
    float term2 = 2.0 * ci * a;
    float rs = (term1 - term2) / (term1 + term2);
    float term3 = a2pb2 * c2 + s4;
    float term4 = term2 * s2;
    float rp = rs * (term3 - term4) / (term3 + term4);
    return 0.5 * (rs + rp);
}

float mf_d(bool ggx, vec2 a, vec3 m) {
    if (m.z <= 0.0) return 0.0;
    float c2 = m.z * m.z;
    vec2 xa = m.xy / a;
    float q = dot(xa, xa);
    if (ggx) {
        float t = q + c2;
        return 1.0 / (PI * a.x * a.y * t * t);
    }
    return exp(-q / c2) / (PI * a.x * a.y * c2 * c2);
}

// Smith's G1: Beckmann's rational fit, GGX exact (Mitsuba's smith_g1).
float mf_g1(bool ggx, vec2 a, vec3 v, vec3 m) {
    if (dot(v, m) * v.z <= 0.0) return 0.0;
    float xy = dot(a * v.xy, a * v.xy);
    if (xy == 0.0) return 1.0;
    float t2 = xy / (v.z * v.z);
    if (ggx) return 2.0 / (1.0 + sqrt(1.0 + t2));
    float b = inversesqrt(t2);
    if (b >= 1.6) return 1.0;
    return (3.535 * b + 2.181 * b * b) / (1.0 + 2.276 * b + 2.577 * b * b);
}

// roughplastic's external transmittance at cos c (linear in its 64-entry table).
float rough_t(int base, float c) {
    float x = clamp(c, 0.0, 1.0) * 63.0;
    int i = min(int(x), 62);
    float f = x - float(i);
    vec4 r0 = texelFetch(u_bsdf, base + 4 + i / 4);
    vec4 r1 = texelFetch(u_bsdf, base + 4 + (i + 1) / 4);
    return mix(r0[i % 4], r1[(i + 1) % 4], f);
}

// The surface of material ``mat`` at p (shading normal ns facing the camera) seen from the camera.
Surf make_surf(int mat, vec3 brdf, vec3 p, vec3 ns, bool front) {
    Surf s;
    s.base = BSDF_ROWS * mat;
    s.kind = int(texelFetch(u_bsdf, s.base).x + 0.5);
    s.brdf = brdf;
    s.ns = ns;
    s.local = frame_from(ns);
    s.wi = s.local * normalize(u_cam_pos - p);
    s.front = front;
    return s;
}

// BSDF times cos(wo) of a glossy surface for the local light direction wo (delta lobes: 0).
vec3 glossy_eval(Surf s, vec3 wo) {
    vec3 wi = s.wi;
    if (!s.front || wi.z <= 0.0 || wo.z <= 0.0 || s.kind == K_CONDUCTOR) return vec3(0.0);
    vec4 r0 = texelFetch(u_bsdf, s.base);
    vec4 r1 = texelFetch(u_bsdf, s.base + 1);
    vec4 r2 = texelFetch(u_bsdf, s.base + 2);
    vec4 r3 = texelFetch(u_bsdf, s.base + 3);
    bool ggx = r0.y != 0.0;
    vec2 a = r0.zw;
    if (s.kind == K_PLASTIC || s.kind == K_ROUGHPLASTIC) {
        float eta = r1.w;
        vec3 d = r1.rgb;
        vec3 denom = 1.0 - (r3.y != 0.0 ? d * r3.x : vec3(r3.x));
        if (s.kind == K_PLASTIC) {
            float k = r2.w * (1.0 - fresnel_dielectric(wi.z, eta))
                      * (1.0 - fresnel_dielectric(wo.z, eta)) * wo.z / PI;
            return d / denom * k;
        }
        vec3 h = normalize(wi + wo);
        float spec = fresnel_dielectric(dot(wi, h), eta) * mf_d(ggx, a, h)
                     * mf_g1(ggx, a, wi, h) * mf_g1(ggx, a, wo, h) / (4.0 * wi.z);
        float k = r2.w * wo.z * rough_t(s.base, wi.z) * rough_t(s.base, wo.z) / PI;
        return spec * r2.rgb + d / denom * k;
    }
    // roughconductor
    vec3 h = normalize(wi + wo);
    float base = mf_d(ggx, a, h) * mf_g1(ggx, a, wi, h) * mf_g1(ggx, a, wo, h) / (4.0 * wi.z);
    float c = dot(wi, h);
    vec3 f = vec3(fresnel_conductor(c, r1.x, r2.x), fresnel_conductor(c, r1.y, r2.y),
                  fresnel_conductor(c, r1.z, r2.z));
    return base * f * r3.rgb;
}

// Reflected light per unit incident radiance/irradiance from the world direction l (unit,
// towards the light): Lambert's albedo / pi * cos, or the glossy BSDF times cos.
vec3 reflect_cos(Surf s, vec3 l) {
    if (s.kind == K_LAMBERT) return s.brdf * max(dot(s.ns, l), 0.0);
    return glossy_eval(s, s.local * l);
}

// The delta lobe's reflectance towards the mirror direction (smooth conductor: its Fresnel;
// smooth plastic: the coating's Fresnel times specular_reflectance); 0 for the others.
vec3 mirror_weight(Surf s) {
    if (!s.front || s.wi.z <= 0.0) return vec3(0.0);
    if (s.kind == K_CONDUCTOR) {
        vec4 r1 = texelFetch(u_bsdf, s.base + 1);
        vec4 r2 = texelFetch(u_bsdf, s.base + 2);
        vec4 r3 = texelFetch(u_bsdf, s.base + 3);
        float c = s.wi.z;
        return r3.rgb * vec3(fresnel_conductor(c, r1.x, r2.x), fresnel_conductor(c, r1.y, r2.y),
                             fresnel_conductor(c, r1.z, r2.z));
    }
    if (s.kind == K_PLASTIC) {
        return texelFetch(u_bsdf, s.base + 2).rgb
               * fresnel_dielectric(s.wi.z, texelFetch(u_bsdf, s.base + 1).w);
    }
    return vec3(0.0);
}
#endif
#ifdef SHADOWS
#if (N_DIR + N_POINT + N_SPOT) > 0
uniform sampler2DArrayShadow u_shadow;       // sharp shadow maps (sun, point cube faces, spot)
uniform mat4 u_shadow_mat[N_DIR + 6 * N_POINT + N_SPOT];    // shadow clip from world
uniform float u_shadow_texel[N_DIR + 6 * N_POINT + N_SPOT]; // texel size at light-view depth 1
#endif
#if N_AREA > 0
uniform sampler2DArrayShadow u_area_shadow;  // one map per area-light sample point
// per sample point (light i, sample j at i * AREA_K * AREA_K + j): 5 texels, the 4 columns of
// its shadow clip_from_world, then (sample position xyz, texel size at light-view depth 1).
// A texture buffer, not uniform arrays: 64 lights x 16 samples would exceed the uniform limit.
uniform samplerBuffer u_area_samples;
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

#if N_AREA > 0
uniform float u_area_offset;  // in texels
// Visibility of an area-light sample point, as shadow_lookup, but the receiver moves towards the
// sample point (along l, by u_area_offset texels times the tangent of the incidence angle, at
// most 8) instead of along its normal: the point stays on its ray to the light sample, so the
// shadow is not displaced (a normal offset shifts soft shadows by a visible fraction of their
// width on receivers at grazing incidence), only the compared depth gets the slope's margin.
float area_shadow_lookup(mat4 m, float texel, int layer, vec3 p, vec3 l, float cos_l, float w0) {
    float sin_l = sqrt(max(0.0, 1.0 - cos_l * cos_l));
    vec3 q = p + l * (u_area_offset * texel * max(w0, 0.0) * min(sin_l / max(cos_l, 1e-3), 8.0));
    vec4 c = m * vec4(q, 1.0);
    if (c.w <= 0.0) return 1.0;
    vec3 ndc = c.xyz / c.w;
    if (any(greaterThan(abs(ndc), vec3(1.0)))) return 1.0;
    vec3 s = ndc * 0.5 + 0.5;
    return texture(u_area_shadow, vec4(s.xy, float(layer), s.z));
}
#endif
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
uniform vec3 u_spot_cos[N_SPOT]; // cos(inner), cos(outer), profile (0 smoothstep, 1 linear)
#endif
#if N_AREA > 0
// Polygon i: vertices u_area_v[4 i .. 4 i + 3], counter-clockwise seen from the emitting side;
// a triangle repeats its last vertex (a zero-length edge adds nothing to Lambert's sum).
uniform vec3 u_area_v[4 * N_AREA];
uniform vec3 u_area_L[N_AREA];   // radiance

// Irradiance / radiance of the polygon (v0, v1, v2, v3) at p with normal n: Lambert's formula
// 1/2 sum_i Theta_i (n . gamma_i), after clipping the polygon to the upper hemisphere of n.
float polygon_irradiance(vec3 v0, vec3 v1, vec3 v2, vec3 v3, vec3 p, vec3 n) {
    vec3 q[4] = vec3[4](v0 - p, v1 - p, v2 - p, v3 - p);
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

// Visibility fraction of area light i (vertices v0..v3, emitting normal nl) at p (shading normal
// ns, geometric ng; w0 its depth along nl): shadow tests towards AREA_K^2 stratified points on
// the light (equal cells) weighted by their unshadowed contribution cos * cos' / r^2 (1 without
// shadows). ``partial`` is set when some sample is (partly) hidden and some not.
float area_visibility(int i, vec3 p, vec3 ns, vec3 ng, vec3 nl, float w0, inout bool partial) {
#ifdef SHADOWS
    float wsum = 0.0;
    float vsum = 0.0;
    float vmin = 1.0;
    float vmax = 0.0;
    for (int j = 0; j < AREA_K * AREA_K; ++j) {
        int layer = i * AREA_K * AREA_K + j;
        vec4 st = texelFetch(u_area_samples, 5 * layer + 4);
        vec3 d = st.xyz - p;
        float r2 = dot(d, d);
        vec3 l = d * inversesqrt(r2);
        float w = max(dot(ns, l), 0.0) * max(-dot(nl, l), 0.0) / r2;
        if (w <= 0.0) continue;
        mat4 sm = mat4(texelFetch(u_area_samples, 5 * layer),
                       texelFetch(u_area_samples, 5 * layer + 1),
                       texelFetch(u_area_samples, 5 * layer + 2),
                       texelFetch(u_area_samples, 5 * layer + 3));
        float v = area_shadow_lookup(sm, st.w, layer, p, l, max(dot(ng, l), 0.0), w0);
        wsum += w;
        vsum += w * v;
        vmin = min(vmin, v);
        vmax = max(vmax, v);
    }
    partial = partial || vmax - vmin > 1e-3;
    return wsum > 0.0 ? vsum / wsum : 1.0;
#else
    return 1.0;
#endif
}

// Irradiance / radiance of area light i at p (shading normal ns, geometric ng), shadowed: the
// exact polygon irradiance times the visibility fraction (area_visibility).
float area_irradiance(int i, vec3 p, vec3 ns, vec3 ng, inout bool partial) {
    vec3 v0 = u_area_v[4 * i];
    vec3 v1 = u_area_v[4 * i + 1];
    vec3 v2 = u_area_v[4 * i + 2];
    vec3 v3 = u_area_v[4 * i + 3];
    vec3 nl = normalize(cross(v1 - v0, v3 - v0));
    float w0 = dot(p - v0, nl);  // depth in every sample's view (axis nl)
    if (w0 <= 0.0) return 0.0;  // behind the emitter (one-sided)
    float e = polygon_irradiance(v0, v1, v2, v3, p, ns);
    if (e <= 0.0) return 0.0;
    return e * area_visibility(i, p, ns, ng, nl, w0, partial);
}

#ifdef GLOSSY
// Reflected radiance of area light i off a glossy surface at p: the BSDF integrated over the
// polygon by the midpoint rule at GLOSSY_N x GLOSSY_N points of its bilinear parametrisation
// (unshadowed), plus the delta lobe's mirror image of the light (exact), both times the light's
// visibility fraction (area_visibility, as the Lambertian path).
vec3 area_glossy(int i, vec3 p, vec3 ng, Surf s, inout bool partial) {
    vec3 v0 = u_area_v[4 * i];
    vec3 v1 = u_area_v[4 * i + 1];
    vec3 v2 = u_area_v[4 * i + 2];
    vec3 v3 = u_area_v[4 * i + 3];
    vec3 nl = normalize(cross(v1 - v0, v3 - v0));
    float w0 = dot(p - v0, nl);
    if (w0 <= 0.0) return vec3(0.0);
    vec3 sum = vec3(0.0);
    for (int y = 0; y < GLOSSY_N; ++y) {
        for (int x = 0; x < GLOSSY_N; ++x) {
            vec2 uv = (vec2(x, y) + 0.5) / float(GLOSSY_N);
            vec3 q = mix(mix(v0, v1, uv.x), mix(v3, v2, uv.x), uv.y);
            vec3 du = mix(v1 - v0, v2 - v3, uv.y);
            vec3 dv = mix(v3 - v0, v2 - v1, uv.x);
            vec3 d = q - p;
            float r2 = dot(d, d);
            vec3 l = d * inversesqrt(r2);
            float cl = -dot(nl, l);
            if (cl <= 0.0 || dot(ng, l) <= 0.0) continue;
            sum += glossy_eval(s, s.local * l) * (cl * length(cross(du, dv)) / r2);
        }
    }
    sum /= float(GLOSSY_N * GLOSSY_N);
    vec3 mw = mirror_weight(s);
    if (max(mw.r, max(mw.g, mw.b)) > 0.0) {  // the mirror ray meets the polygon?
        vec3 r = reflect(-normalize(u_cam_pos - p), s.ns);
        float dn = dot(r, nl);
        if (dn < 0.0) {
            vec3 x = p + r * (dot(v0 - p, nl) / dn);
            vec3 q[4] = vec3[4](v0, v1, v2, v3);
            bool inside = true;
            for (int k = 0; k < 4; ++k)
                inside = inside && dot(cross(q[(k + 1) % 4] - q[k], x - q[k]), nl) >= 0.0;
            if (inside) sum += mw;
        }
    }
    if (max(sum.r, max(sum.g, sum.b)) <= 0.0) return vec3(0.0);
    return u_area_L[i] * sum * area_visibility(i, p, s.ns, ng, nl, w0, partial);
}
#endif
#endif

float spot_falloff(float c, vec3 cs) {
    if (cs.z > 0.5) {  // linear in the angle (Mitsuba's spot)
        float a_in = acos(cs.x), a_out = acos(cs.y);
        return clamp((a_out - acos(clamp(c, -1.0, 1.0))) / (a_out - a_in), 0.0, 1.0);
    }
    float x = clamp((c - cs.y) / (cs.x - cs.y), 0.0, 1.0);
    return x * x * (3.0 - 2.0 * x);
}
#endif  // LOC_DL

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    float id = texelFetch(u_vis, px, 0).r;
    if (id == 0.0) {  // background
#ifdef LOC_A
        o_albedo = vec4(0.0);
#endif
#ifdef LOC_N
        o_normal = vec4(0.0);
#endif
#ifdef LOC_P
        o_pos = vec4(0.0);
#endif
#ifdef LOC_DL
#ifdef HAS_SKY
        o_dl = vec4(sky_radiance(), 0.0);
#else
        o_dl = vec4(0.0);
#endif
#endif
        return;
    }
    bool front = id > 0.0;
    int fi = int(abs(id) + 0.5) - 1;
    ivec4 tri = texelFetch(u_tris, fi);
    int mat = tri.w;
    vec4 a0 = texelFetch(u_verts, 2 * tri.x);
    vec4 a1 = texelFetch(u_verts, 2 * tri.y);
    vec4 a2 = texelFetch(u_verts, 2 * tri.z);
    vec3 e1 = a1.xyz - a0.xyz;
    vec3 e2 = a2.xyz - a0.xyz;
    // the rasterizer samples at the pixel centre, inside the face: clamp rounding excursions
    vec2 b = barycentrics(pixel_ray(0.0, 0.0), a0.xyz, e1, e2);
    b = max(b, 0.0);
    b /= max(1.0, b.x + b.y);
    float b0 = 1.0 - b.x - b.y;
    vec3 p = b0 * a0.xyz + b.x * a1.xyz + b.y * a2.xyz;
#if defined(LOC_N) || defined(LOC_DL) || defined(HAS_TEX)
    vec4 n0 = texelFetch(u_verts, 2 * tri.x + 1);  // (normal, v)
    vec4 n1 = texelFetch(u_verts, 2 * tri.y + 1);
    vec4 n2 = texelFetch(u_verts, 2 * tri.z + 1);
#endif
#if defined(LOC_N) || defined(LOC_DL)
    // Two-sided surfaces: seen from behind, both normals are flipped to face the camera.
    vec3 ns = normalize(b0 * n0.xyz + b.x * n1.xyz + b.y * n2.xyz);
    if (!front) ns = -ns;
#endif
#if defined(LOC_A) || defined(LOC_DL)
    vec4 m0 = texelFetch(u_materials, 2 * mat);
    vec3 albedo = m0.rgb;
#ifdef HAS_TEX
    if (m0.w >= 0.0) {
        vec2 t0 = vec2(a0.w, n0.w);
        vec2 tu = vec2(a1.w, n1.w) - t0;
        vec2 tv = vec2(a2.w, n2.w) - t0;
        vec2 uv = t0 + b.x * tu + b.y * tv;
        // Footprint as the rasterizer takes it: uv differences across this pixel's 2x2 quad (its
        // first pixel to the next right and the next up), on this face's plane.
        vec2 q = vec2(ivec2(gl_FragCoord.xy) & 1);  // position in the quad
        vec2 bq = barycentrics(pixel_ray(-q.x, -q.y), a0.xyz, e1, e2);
        vec2 bx = barycentrics(pixel_ray(1.0 - q.x, -q.y), a0.xyz, e1, e2) - bq;
        vec2 by = barycentrics(pixel_ray(-q.x, 1.0 - q.y), a0.xyz, e1, e2) - bq;
        vec2 ddx = bx.x * tu + bx.y * tv;
        vec2 ddy = by.x * tu + by.y * tv;
        albedo *= textureGrad(u_textures, vec3(uv, m0.w), ddx, ddy).rgb;
    }
#endif
#endif

#ifdef LOC_DL
    vec4 face = texelFetch(u_faces, fi);
    vec3 ng = front ? face.xyz : -face.xyz;
    vec3 dl = front ? texelFetch(u_materials, 2 * mat + 1).rgb : vec3(0.0);
    vec3 brdf = albedo / PI;
#ifdef GLOSSY
    Surf surf = make_surf(mat, brdf, p, ns, front);
    bool glossy = surf.kind != K_LAMBERT;
#define REFLECT_COS(l) reflect_cos(surf, l)
#else
#define REFLECT_COS(l) (brdf * max(dot(ns, l), 0.0))
#endif
#if N_DIR > 0
    for (int i = 0; i < N_DIR; ++i) {
        vec3 l = -u_dir_dir[i];
        float cg = dot(ng, l);
        if (cg <= 0.0) continue;
        float vis = 1.0;
#ifdef SHADOWS
        vis = shadow_lookup(u_shadow, u_shadow_mat[i], u_shadow_texel[i], i, p, ng, cg, 1.0);
#endif
        dl += REFLECT_COS(l) * u_dir_E[i] * vis;
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
        dl += REFLECT_COS(l) * u_point_I[i] / r2 * vis;
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
        dl += REFLECT_COS(l) * u_spot_I[i] * fall / r2 * vis;
    }
#endif
#if N_AREA > 0
    // Area lights, with the tracer's pixel filter where it matters: a pixel some of whose light
    // samples are hidden (a penumbra) is shaded again at AREA_SUB x AREA_SUB stratified points of
    // its footprint on the face's plane (box filter), as the tracer's jittered pixels integrate
    // it; at one point per pixel the penumbra's curved profile is biased (dark at its umbra side).
    bool partial = false;
    vec3 area = vec3(0.0);
    // glossy materials: the reflected radiance itself (area_glossy); Lambert: the irradiance
#ifdef GLOSSY
    if (glossy) {
        for (int i = 0; i < N_AREA; ++i) area += area_glossy(i, p, ng, surf, partial);
    } else
#endif
    for (int i = 0; i < N_AREA; ++i) area += u_area_L[i] * area_irradiance(i, p, ns, ng, partial);
#if AREA_SUB > 1
    if (partial) {
        area = vec3(0.0);
        for (int sy = 0; sy < AREA_SUB; ++sy) {
            for (int sx = 0; sx < AREA_SUB; ++sx) {
                vec2 o = (vec2(sx, sy) + 0.5) / float(AREA_SUB) - 0.5;
                vec2 bs = barycentrics(pixel_ray(o.x, o.y), a0.xyz, e1, e2);
                vec3 ps = a0.xyz + bs.x * e1 + bs.y * e2;
                vec3 nss = normalize((1.0 - bs.x - bs.y) * n0.xyz + bs.x * n1.xyz + bs.y * n2.xyz);
                if (!front) nss = -nss;
                bool unused = false;
#ifdef GLOSSY
                if (glossy) {
                    Surf ss = make_surf(mat, brdf, ps, nss, front);
                    for (int i = 0; i < N_AREA; ++i) area += area_glossy(i, ps, ng, ss, unused);
                    continue;
                }
#endif
                for (int i = 0; i < N_AREA; ++i)
                    area += u_area_L[i] * area_irradiance(i, ps, nss, ng, unused);
            }
        }
        area /= float(AREA_SUB * AREA_SUB);
    }
#endif
#ifdef GLOSSY
    dl += glossy ? area : brdf * area;
#else
    dl += brdf * area;
#endif
#endif
    o_dl = vec4(dl, 1.0);
#endif
#ifdef LOC_A
    o_albedo = vec4(albedo, 1.0);
#endif
#ifdef LOC_N
    o_normal = vec4(ns, 1.0);
#endif
#ifdef LOC_P
    o_pos = vec4(p, dot(p - u_cam_pos, u_cam_forward));
#endif
}
