// The inverse search's shared declarations (passes flow_patch and flow_patch_group): its buffers, the patch's
// pixel count, the Hessian's Tikhonov term and the initial flow read at a patch's centre.
#include "flow_common.glsl"

layout(std430, binding = 4) READS buffer InitBuf { vec2 init_[]; };     // (H, W) initial dense flow
layout(std430, binding = 5) WRITES buffer PatchBuf { vec2 patch_[]; };  // (rows, columns) patch flows
layout(std430, binding = 8) READS buffer PrevBuf { vec2 prev_[]; };     // previous sweep's patch flows

uniform int iterations;

const int N = PATCH * PATCH;
const float EPS = 1e-2;  // Tikhonov term of the Hessian (levels^2): flat or 1-pixel patches stay put

// the initial dense flow at index coordinates p, bilinear, clamped to the level
vec2 init_at(vec2 p) {
    p = clamp(p, vec2(0.0), vec2(float(size.y - 1), float(size.x - 1)));
    ivec2 f = ivec2(floor(p));
    vec2 t = p - vec2(f);
    ivec2 g = min(f + 1, ivec2(size.y - 1, size.x - 1));
    vec2 top = mix(init_[f.y * size.y + f.x], init_[f.y * size.y + g.x], t.x);
    vec2 bottom = mix(init_[g.y * size.y + f.x], init_[g.y * size.y + g.x], t.x);
    return mix(top, bottom, t.y);
}
