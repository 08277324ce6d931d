"""GLSL 3.30 sources of the scene renderer (kept in Python so packaging needs no data files).

Camera space in every shader is OpenCV's (x right, y down, z forward); ``u_proj`` maps it to GL clip space
(see ``render.clip_from_camera``), so images come out of GL bottom-up and are flipped on readback.
"""

# ------------------------------------------------------------------ shared noise (integer hashes, no sin())
NOISE = """
uniform uint u_seed;

uint pcg(uint v) {
    uint state = v * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}
float hash3(ivec3 p) {
    uvec3 q = uvec3(p);
    return float(pcg(q.x * 73856093u ^ q.y * 19349663u ^ q.z * 83492791u ^ u_seed) >> 8) * (1.0 / 16777216.0);
}
float hash2(ivec2 p) { return hash3(ivec3(p, 7)); }
vec2 hash22(ivec2 p) { return vec2(hash3(ivec3(p, 11)), hash3(ivec3(p, 13))); }

float vnoise3(vec3 x) {
    vec3 fl = floor(x);
    ivec3 i = ivec3(fl);
    vec3 f = x - fl;
    vec3 u = f * f * (3.0 - 2.0 * f);
    float a = hash3(i), b = hash3(i + ivec3(1, 0, 0));
    float c = hash3(i + ivec3(0, 1, 0)), d = hash3(i + ivec3(1, 1, 0));
    float e = hash3(i + ivec3(0, 0, 1)), g = hash3(i + ivec3(1, 0, 1));
    float h = hash3(i + ivec3(0, 1, 1)), k = hash3(i + ivec3(1, 1, 1));
    return mix(mix(mix(a, b, u.x), mix(c, d, u.x), u.y), mix(mix(e, g, u.x), mix(h, k, u.x), u.y), u.z);
}
float vnoise2(vec2 x) {
    vec2 fl = floor(x);
    ivec2 i = ivec2(fl);
    vec2 f = x - fl;
    vec2 u = f * f * (3.0 - 2.0 * f);
    float a = hash2(i), b = hash2(i + ivec2(1, 0)), c = hash2(i + ivec2(0, 1)), d = hash2(i + ivec2(1, 1));
    return mix(mix(a, b, u.x), mix(c, d, u.x), u.y);
}
float fbm3(vec3 x, int octaves) {
    float sum = 0.0, amp = 0.5, norm = 0.0;
    for (int i = 0; i < octaves; ++i) {
        sum += amp * vnoise3(x);
        norm += amp;
        x = x * 2.03 + vec3(17.1, 3.7, 9.2);
        amp *= 0.5;
    }
    return sum / norm;
}
float fbm2(vec2 x, int octaves) {
    float sum = 0.0, amp = 0.5, norm = 0.0;
    for (int i = 0; i < octaves; ++i) {
        sum += amp * vnoise2(x);
        norm += amp;
        x = mat2(1.6, 1.2, -1.2, 1.6) * x + vec2(5.3, 1.7);
        amp *= 0.5;
    }
    return sum / norm;
}
"""

# ------------------------------------------------------------------ geometry, colour pass
# the geometry's vertices, for the colour pass and the live pass: the point in camera(t) (``v_cam``) and where it
# was in the previous frame's camera (``v_cam_prev``, the live pass's motion vectors; the colour pass does not
# read it, so its program drops it)
GEOMETRY_VS = """
#version 330
in vec3 in_pos;
in vec3 in_nrm;
uniform mat4 u_model;              // world_from_object at t
uniform mat4 u_cam_from_obj;       // OpenCV camera(t) from object(t), composed in float64
uniform mat4 u_prev_cam_from_obj;  // camera(previous frame) from object(previous frame): where the point was
uniform mat4 u_proj;
out vec3 v_obj;
out vec3 v_obj_nrm;
out vec3 v_world;
out vec3 v_nrm;
out vec3 v_cam;
out vec3 v_cam_prev;
void main() {
    v_obj = in_pos;
    v_obj_nrm = in_nrm;
    v_world = (u_model * vec4(in_pos, 1.0)).xyz;
    v_nrm = mat3(u_model) * in_nrm;
    vec4 cam = u_cam_from_obj * vec4(in_pos, 1.0);
    v_cam = cam.xyz;
    v_cam_prev = (u_prev_cam_from_obj * vec4(in_pos, 1.0)).xyz;
    gl_Position = u_proj * cam;
}
"""


SKY_FUNCTION = """
uniform vec3 u_zenith, u_horizon, u_below, u_cloud_col;
uniform float u_coverage, u_cloud_scale, u_sun_disk, u_sun_cos;
uniform vec3 u_sun_dir, u_sun_col;
vec3 sky_color(vec3 d) {
    float e = d.z;
    vec3 col = e > 0.0 ? mix(u_horizon, u_zenith, sqrt(e)) : mix(u_horizon, u_below, min(-e * 6.0, 1.0));
    float cs = max(dot(d, u_sun_dir), 0.0);
    col += u_sun_col * 0.25 * pow(cs, 12.0);
    if (e > 0.0) {
        vec2 q = d.xy / (e + 0.08) * u_cloud_scale;
        float c = fbm2(q, 5);
        float cover = smoothstep(0.62 - 0.36 * u_coverage, 0.74 - 0.3 * u_coverage, c);
        vec3 cloud = u_cloud_col * (0.65 + 0.5 * fbm2(q * 2.7 + 3.1, 3));
        col = mix(col, cloud, cover * smoothstep(0.0, 0.12, e));
        if (cs > u_sun_cos) col += vec3(u_sun_disk) * (1.0 - cover);
    }
    return col;
}
"""

# the surface's shading, ``vec3 shade()``: what the colour pass (GEOMETRY_FS) and the live pass (LIVE_FS) both
# write, from the same inputs, so that the two passes give the same colour
SHADING = """
in vec3 v_obj;
in vec3 v_obj_nrm;
in vec3 v_world;
in vec3 v_nrm;

uniform int u_pattern;
uniform vec3 u_col0, u_col1, u_col2;
uniform float u_scale, u_detail, u_macro, u_specular, u_shininess;
uniform mat3 u_tex_rot;
uniform mat2 u_tex_rot2;
uniform vec3 u_tex_offset;

uniform vec3 u_eye;
uniform vec3 u_sun_dir, u_sun_col, u_amb_sky, u_amb_ground;
uniform int u_num_lights;
uniform vec3 u_light_pos[4];
uniform vec3 u_light_col[4];
uniform float u_fog;
uniform vec3 u_fog_col;
uniform int u_shadows;
uniform sampler2DShadow u_shadow_map;
uniform mat4 u_shadow_mat;
uniform float u_shadow_texel;
""" + NOISE + """
vec2 plane_coords() {
    vec3 a = abs(v_obj_nrm);
    vec2 uv = a.z >= a.x && a.z >= a.y ? v_obj.xy : (a.x >= a.y ? v_obj.yz : v_obj.xz);
    return u_tex_rot2 * uv * u_scale + u_tex_offset.xy;
}

vec3 albedo() {
    vec3 p = u_tex_rot * (v_obj * u_scale) + u_tex_offset;
    vec3 col;
    if (u_pattern == 0) {                       // noise: fBm blend of two colours + accent blotches
        float n = fbm3(p, 5);
        float m = vnoise3(p * 2.7 + 11.0);
        col = mix(mix(u_col0, u_col1, smoothstep(0.3, 0.7, n)), u_col2, 0.7 * smoothstep(0.62, 0.8, m));
    } else if (u_pattern == 1) {                // checker, noise-modulated
        vec2 q = floor(plane_coords());
        col = mod(q.x + q.y, 2.0) < 0.5 ? u_col0 : u_col1;
        col *= 0.7 + 0.6 * vnoise3(p * 3.0);
    } else if (u_pattern == 2) {                // stripes with warped edges and thin accent lines
        float w = fract(p.x + 0.35 * fbm3(p * 0.6, 3));
        col = w < 0.5 ? u_col0 : u_col1;
        col = abs(w - 0.5) < 0.04 ? u_col2 : col;
    } else if (u_pattern == 3) {                // cells (Voronoi): per-cell colour, dark edges
        vec2 uv = plane_coords();
        vec2 cell = floor(uv), f = uv - cell;
        float d1 = 8.0, d2 = 8.0;
        ivec2 id = ivec2(0);
        for (int j = -1; j <= 1; ++j)
            for (int i = -1; i <= 1; ++i) {
                ivec2 g = ivec2(cell) + ivec2(i, j);
                vec2 r = vec2(i, j) + hash22(g) - f;
                float d = dot(r, r);
                if (d < d1) { d2 = d1; d1 = d; id = g; } else if (d < d2) { d2 = d; }
            }
        col = mix(u_col0, u_col1, hash2(id));
        col = mix(u_col2, col, smoothstep(0.02, 0.08, sqrt(d2) - sqrt(d1)));
    } else if (u_pattern == 4) {                // bricks with mortar and per-brick tint
        vec2 uv = plane_coords() * vec2(1.0, 2.0);
        float row = floor(uv.y);
        uv.x += 0.5 * mod(row, 2.0);
        vec2 cell = floor(uv), f = uv - cell;
        float mortar = min(min(f.x, 1.0 - f.x) * 1.0, min(f.y, 1.0 - f.y) * 0.5);
        col = mix(u_col0, u_col1, hash2(ivec2(cell)));
        col = mortar < 0.03 ? u_col2 : col * (0.8 + 0.4 * vnoise3(p * 4.0));
    } else {                                    // marble: warped sine bands with veins
        float t = sin(p.x * 3.0 + 7.0 * fbm3(p * 0.7, 4));
        col = mix(u_col0, u_col1, 0.5 + 0.5 * t);
        col = mix(u_col2, col, smoothstep(0.0, 0.12, abs(t)));
    }
    float fine = vnoise3(p * 9.0) - 0.5, coarse = vnoise3(p * 0.13 + 5.0) - 0.5;
    return col * (1.0 + u_detail * fine) * (1.0 + u_macro * coarse);
}

float sun_shadow(vec3 world, vec3 n) {
    if (u_shadows == 0) return 1.0;
    vec4 s = u_shadow_mat * vec4(world + n * (1.5 * u_shadow_texel), 1.0);
    vec3 c = s.xyz / s.w;
    if (any(lessThan(c, vec3(0.0))) || any(greaterThan(c, vec3(1.0)))) return 1.0;
    float texel = 1.0 / float(textureSize(u_shadow_map, 0).x);
    float sum = 0.0;
    for (int j = 0; j < 2; ++j)
        for (int i = 0; i < 2; ++i)
            sum += texture(u_shadow_map, vec3(c.xy + (vec2(i, j) - 0.5) * texel, c.z - 0.0005));
    return 0.25 * sum;
}

vec3 shade() {
    vec3 n = normalize(v_nrm);
    if (!gl_FrontFacing) n = -n;
    vec3 base = albedo();
    vec3 to_eye = u_eye - v_world;
    float dist = length(to_eye);
    vec3 v = to_eye / dist;
    float gloss = u_specular * (u_shininess + 2.0) / 8.0;

    float ndl = dot(n, u_sun_dir);
    vec3 col = base * mix(u_amb_ground, u_amb_sky, 0.5 + 0.5 * n.z);
    if (ndl > 0.0) {
        float sh = sun_shadow(v_world, n);
        float spec = gloss * pow(max(dot(n, normalize(u_sun_dir + v)), 0.0), u_shininess);
        col += u_sun_col * sh * (base * ndl + spec * ndl);
    }
    for (int i = 0; i < u_num_lights; ++i) {
        vec3 l = u_light_pos[i] - v_world;
        float d2 = max(dot(l, l), 0.05);
        l *= inversesqrt(d2);
        float nl = dot(n, l);
        if (nl > 0.0) {
            float spec = gloss * pow(max(dot(n, normalize(l + v)), 0.0), u_shininess);
            col += u_light_col[i] / d2 * nl * (base + spec);
        }
    }
    col = mix(u_fog_col, col, exp(-u_fog * dist));
    return max(col, vec3(0.0));
}
"""

GEOMETRY_FS = """
#version 330
out vec4 f_color;
""" + SHADING + """
void main() { f_color = vec4(shade(), 1.0); }
"""

# ------------------------------------------------------------------ full-screen passes
FULLSCREEN_VS = """
#version 330
in vec2 in_xy;
void main() { gl_Position = vec4(in_xy, 1.0, 1.0); }   // at the far plane: fills only empty pixels
"""

SKY_COLOR_FS = """
#version 330
out vec4 f_color;
uniform mat3 u_world_from_pixel;   // world ray direction of image pixel (u, v, 1), v from the top
uniform float u_height;
""" + NOISE + SKY_FUNCTION + """
void main() {
    vec2 uv = vec2(gl_FragCoord.x, u_height - gl_FragCoord.y);
    vec3 d = normalize(u_world_from_pixel * vec3(uv, 1.0));
    f_color = vec4(max(sky_color(d), vec3(0.0)), 1.0);
}
"""

DOWNSAMPLE_FS = """
#version 330
out vec4 f_color;
uniform sampler2D u_image;
uniform int u_factor;
void main() {
    ivec2 base = ivec2(gl_FragCoord.xy) * u_factor;
    vec4 sum = vec4(0.0);
    for (int j = 0; j < u_factor; ++j)
        for (int i = 0; i < u_factor; ++i)
            sum += texelFetch(u_image, base + ivec2(i, j), 0);
    f_color = sum / float(u_factor * u_factor);
}
"""

# ------------------------------------------------------------------ ground truth pass
TRUTH_VS = """
#version 330
in vec3 in_pos;
uniform mat4 u_cam_from_obj;        // camera(t)   from object(t)
uniform mat4 u_cam1_from_obj1;      // camera(t+1) from object(t+1)
uniform mat4 u_cam_from_obj1;       // camera(t)   from object(t+1)
uniform mat4 u_proj;
out vec3 v_cam;
out vec3 v_cam_next;
out vec3 v_cam_objnext;
void main() {
    vec4 p = vec4(in_pos, 1.0);
    v_cam = (u_cam_from_obj * p).xyz;
    v_cam_next = (u_cam1_from_obj1 * p).xyz;
    v_cam_objnext = (u_cam_from_obj1 * p).xyz;
    gl_Position = u_proj * vec4(v_cam, 1.0);
}
"""

PROJECT = """
uniform vec4 u_k;      // fx, fy, cx, cy at t
uniform vec4 u_k1;     // at t+1
vec2 project(vec3 p, vec4 k) {
    float z = max(p.z, 1e-6);   // a point behind the camera gets a huge but finite flow
    return vec2(k.x * p.x / z + k.z, k.y * p.y / z + k.w);
}
"""

TRUTH_FS = """
#version 330
in vec3 v_cam;
in vec3 v_cam_next;
in vec3 v_cam_objnext;
layout(location = 0) out vec4 f_geometry;   // planar depth, object id, moving, 1 (= surface)
layout(location = 1) out vec4 f_flow;       // flow xy, object_flow xy
uniform float u_id;
uniform float u_moving;
""" + PROJECT + """
void main() {
    vec2 here = project(v_cam, u_k);
    f_geometry = vec4(v_cam.z, u_id, u_moving, 1.0);
    f_flow = vec4(project(v_cam_next, u_k1) - here, project(v_cam_objnext, u_k) - here);
}
"""

SKY_TRUTH_FS = """
#version 330
layout(location = 0) out vec4 f_geometry;
layout(location = 1) out vec4 f_flow;
uniform mat3 u_k_inv;
uniform mat3 u_rot;        // R(t+1) R(t)^T: a point at infinity only sees the camera's rotation
uniform float u_height;
""" + PROJECT + """
void main() {
    vec2 here = vec2(gl_FragCoord.x, u_height - gl_FragCoord.y);
    vec3 d = u_rot * (u_k_inv * vec3(here, 1.0));
    f_geometry = vec4(0.0);                   // alpha 0 marks "no surface": depth becomes +inf
    f_flow = vec4(project(d, u_k1) - here, 0.0, 0.0);
}
"""

# ------------------------------------------------------------------ sun shadow map
SHADOW_VS = """
#version 330
in vec3 in_pos;
uniform mat4 u_light_from_obj;
void main() { gl_Position = u_light_from_obj * vec4(in_pos, 1.0); }
"""

SHADOW_FS = """
#version 330
void main() {}
"""

# ------------------------------------------------------------------ live pass: colour, depth and motion vectors
# What a game's G-buffer pass writes, in one draw of the scene: the shaded colour, the planar depth and the
# motion vector of each pixel, computed from the previous frame's object and camera transforms (the vertex is
# moved by both frames' transforms in GEOMETRY_VS and the fragment projects where its point was), as engines
# write them.

MOTION_VECTOR = """
uniform vec3 u_prev_k0;      // the previous camera's intrinsics, row 0 (fx, skew, cx) ...
uniform vec2 u_prev_k1;      // ... and row 1 (fy, cy)
uniform float u_max_vector;  // pixels: a longer vector is no vector (engine.core.frames.MAX_MOTION_DIAGONALS)
uniform float u_height;
// (x, y, 1, 0): the vector in pixels (x right, y down) from this pixel's centre to where point q (in the previous
// camera's axes) was seen; (0, 0, 0, 0) where it has none: q on or behind that camera's plane, or too far
vec4 motion_vector(vec3 q) {
    if (!(q.z > 1e-9 * max(1.0, max(abs(q.x), abs(q.y))))) return vec4(0.0);
    vec2 here = vec2(gl_FragCoord.x, u_height - gl_FragCoord.y);
    vec2 there = vec2(u_prev_k0.x * q.x / q.z + u_prev_k0.y * q.y / q.z + u_prev_k0.z, u_prev_k1.x * q.y / q.z + u_prev_k1.y);
    vec2 mv = there - here;
    if (max(abs(mv.x), abs(mv.y)) > u_max_vector) return vec4(0.0);
    return vec4(mv, 1.0, 0.0);
}
"""

LIVE_FS = """
#version 330
in vec3 v_cam;
in vec3 v_cam_prev;
layout(location = 0) out vec4 f_rgbd;    // linear colour, planar depth (0: no surface)
layout(location = 1) out vec4 f_motion;  // see motion_vector
""" + SHADING + MOTION_VECTOR + """
void main() {
    f_rgbd = vec4(shade(), v_cam.z);
    f_motion = motion_vector(v_cam_prev);
}
"""

SKY_LIVE_FS = """
#version 330
layout(location = 0) out vec4 f_rgbd;
layout(location = 1) out vec4 f_motion;
uniform mat3 u_world_from_pixel;   // world ray direction of image pixel (u, v, 1), v from the top
uniform mat3 u_prev_from_pixel;    // the same ray in the previous camera's axes: only its rotation moves the sky
uniform int u_sky_visible;
""" + NOISE + SKY_FUNCTION + MOTION_VECTOR + """
void main() {
    vec3 uv = vec3(gl_FragCoord.x, u_height - gl_FragCoord.y, 1.0);
    vec3 col = u_sky_visible != 0 ? max(sky_color(normalize(u_world_from_pixel * uv)), vec3(0.0)) : vec3(0.0);
    f_rgbd = vec4(col, 0.0);
    f_motion = motion_vector(u_prev_from_pixel * uv);
}
"""
