// Hole fill pass 3, per pixel: the filled colour (H, W, 3) and the packed hole mask (bit o % 32 of word
// o / 32), gathered per workgroup in shared memory and written whole (the mask needs no clear and no global
// atomics). A hole copies its row source; in a row without a known pixel, the farther (ties: the upper) of
// the nearest rows above / below that have one, resolved to that pixel's own source; with neither, the
// fallback colour (the frame that was warped). Variant WITH_DEPTH: also the filled planar depth (H, W),
// copied from the same source (+inf with none), as engine.geometry.holefill.fill_holes.
#include "fill_common.glsl"

layout(std430, binding = 14) writeonly buffer FilledBuf { float filled_[]; };  // (H, W, 3)
layout(std430, binding = 15) writeonly buffer MaskBuf { uint mask_[]; };       // ceil(H W / 32)
#ifdef WITH_DEPTH
layout(std430, binding = 19) writeonly buffer FilledDepthBuf { float filled_depth_[]; };  // (H, W)
#endif

// depth of pixel (r, x) after the row fill (rows with a known pixel only)
float row_filled_depth(int r, int x) {
    int o = r * size.y + x;
    return hole_[o] != 0u ? warped_[r * size.y + rowsrc_[o]].w : warped_[o].w;
}

const uint GROUP_WORDS = uint(LOCAL_SIZE) / 32u;
shared uint group_mask[GROUP_WORDS];

// pixel o = y W + x of an (H, W) = (h, w) frame
void fill_pixel(int o, int h, int w) {
    int y = o / w, x = o % w;
    vec3 rgb;
    float z;
    if (hole_[o] == 0u) {
        rgb = warped_[o].rgb;
        z = warped_[o].w;
    } else {
        atomicOr(group_mask[(uint(o) % uint(LOCAL_SIZE)) / 32u], 1u << uint(o & 31));
        int src = -1;
        if (rowsrc_[o] >= 0) {
            src = y * w + rowsrc_[o];
        } else {
            int up = links_[2 * y], down = links_[2 * y + 1];
            if (up >= 0 || down >= 0) {
                float depth_up = up >= 0 ? row_filled_depth(up, x) : -INF;
                float depth_down = down >= 0 ? row_filled_depth(down, x) : -INF;
                int r = depth_down > depth_up ? down : up;
                int t = r * w + x;
                src = hole_[t] != 0u ? r * w + rowsrc_[t] : t;
            }
        }
        rgb = src >= 0 ? warped_[src].rgb : vec3(color_[3 * o], color_[3 * o + 1], color_[3 * o + 2]);
        z = src >= 0 ? warped_[src].w : INF;
    }
    filled_[3 * o] = rgb.r;
    filled_[3 * o + 1] = rgb.g;
    filled_[3 * o + 2] = rgb.b;
#ifdef WITH_DEPTH
    filled_depth_[o] = z;
#endif
}

void main() {
    uint i = invocation();
    int h = size.x, w = size.y;
    uint lid = gl_LocalInvocationIndex;
    if (lid < GROUP_WORDS) group_mask[lid] = 0u;
    barrier();
    if (i < uint(h * w)) fill_pixel(int(i), h, w);
    barrier();
    // a workgroup's pixels are consecutive from a multiple of LOCAL_SIZE: its words are whole
    uint word = (i - lid) / 32u + lid;
    if (lid < GROUP_WORDS && word < (uint(h * w) + 31u) / 32u) mask_[word] = group_mask[lid];
}
