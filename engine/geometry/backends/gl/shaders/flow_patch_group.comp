// Flow pass 3, cooperative variant of flow_patch (the same inverse search, the same result up to the order
// of float sums): a patch's PATCH x PATCH pixels are spread over LANES invocations of a workgroup, each
// holding its pixels' template and gradients in registers, and every sum over the patch (gradient means,
// Hessian, the residual's mean, SSD and sum(g e)) is a tree reduction in shared memory. flow_patch runs a
// patch on one invocation with 3 x PATCH^2 floats of state and a serial chain of PATCH^2 samples a cost:
// few invocations, each waiting on memory (about 3 ms a sweep on an H200 at 1080p). Here a cost is one
// sample and two reductions per invocation, over LANES times as many invocations.
// All control flow around a reduction is uniform in the workgroup (barriers): neighbours outside the grid
// and patches past the last are evaluated on a stand-in and their results dropped.
#include "flow_patch_common.glsl"

// LANES (defined by flow.py: PATCH_LANES): invocations per patch, a power of two dividing LOCAL_SIZE
const int PER_LANE = (N + LANES - 1) / LANES;    // pixels per invocation

// Two halves used in turn: a reduction reads its total from one half while the next writes the other, so
// no barrier is needed after the read (and a compiler that sinks that read past a barrier, as llvmpipe's
// does, still reads the right total).
shared vec4 sums_[2 * LOCAL_SIZE];
uint half_ = 0u;  // the half the next reduction uses (the same in every lane: all run every reduction)

// the sum of v over the patch's lanes, the same value in every lane
vec4 patch_sum(vec4 v, uint lane, uint base) {
    uint at = half_ * uint(LOCAL_SIZE) + base;
    half_ = 1u - half_;
    sums_[at + lane] = v;
    memoryBarrierShared();
    barrier();
    for (uint s = uint(LANES) / 2u; s > 0u; s >>= 1u) {
        if (lane < s) sums_[at + lane] += sums_[at + lane + s];
        memoryBarrierShared();
        barrier();
    }
    return sums_[at];
}

int pixel(uint lane, int j) {  // the patch pixel of a lane's j-th slot (slots past the patch: its last pixel)
    return min(int(lane) + j * LANES, N - 1);
}

float weight(uint lane, int j) {  // 1 for a slot on the patch, 0 past it (no branches around the reductions)
    return int(lane) + j * LANES < N ? 1.0 : 0.0;
}

// mean-normalised SSD of the patch at (oy, ox) moved by u, and sum(g e) into step (flow_patch's cost)
float cost(int oy, int ox, vec2 u, out vec2 step, uint lane, uint base, float tmpl[PER_LANE],
           float gx[PER_LANE], float gy[PER_LANE]) {
    float e[PER_LANE];
    float s = 0.0;
    for (int j = 0; j < PER_LANE; ++j) {
        int k = pixel(lane, j);
        e[j] = weight(lane, j) * (second_bilinear(vec2(float(ox + k % PATCH), float(oy + k / PATCH)) + u) - tmpl[j]);
        s += e[j];
    }
    float mean = patch_sum(vec4(s, 0.0, 0.0, 0.0), lane, base).x / float(N);
    vec3 acc = vec3(0.0);
    for (int j = 0; j < PER_LANE; ++j) {
        float d = weight(lane, j) * (e[j] - mean);
        acc += vec3(d * d, gx[j] * d, gy[j] * d);
    }
    vec3 total = patch_sum(vec4(acc, 0.0), lane, base).xyz;
    step = total.yz;
    return total.x;
}

void main() {
    int rows = patch_count(size.x), cols = patch_count(size.y);
    uint lane = gl_LocalInvocationIndex % uint(LANES);
    uint base = gl_LocalInvocationIndex - lane;
    float tmpl[PER_LANE], gx[PER_LANE], gy[PER_LANE];
    uint i = invocation() / uint(LANES);
    bool valid = i < uint(rows * cols);
    if (!valid) i = uint(rows * cols - 1);  // a stand-in: it takes part in the reductions, writes nothing
    int py = int(i) / cols, px = int(i) % cols;
    int oy = patch_origin(py, size.x), ox = patch_origin(px, size.y);
    vec2 g = vec2(0.0);
    for (int j = 0; j < PER_LANE; ++j) {
        int k = pixel(lane, j);
        int y = oy + k / PATCH, x = ox + k % PATCH;
        float w = weight(lane, j);
        tmpl[j] = first_at(y, x);
        gx[j] = w * 0.5 * (first_at(y, x + 1) - first_at(y, x - 1));
        gy[j] = w * 0.5 * (first_at(y + 1, x) - first_at(y - 1, x));
        g += vec2(gx[j], gy[j]);
    }
    g = patch_sum(vec4(g, 0.0, 0.0), lane, base).xy / float(N);
    vec3 h = vec3(0.0);
    for (int j = 0; j < PER_LANE; ++j) {
        float w = weight(lane, j);
        gx[j] -= w * g.x;
        gy[j] -= w * g.y;
        h += vec3(gx[j] * gx[j], gx[j] * gy[j], gy[j] * gy[j]);
    }
    h = patch_sum(vec4(h, 0.0), lane, base).xyz;
    float hxx = EPS + h.x, hxy = h.y, hyy = EPS + h.z;
    float det = hxx * hyy - hxy * hxy;
    mat2 inverse_h = mat2(hyy, -hxy, -hxy, hxx) / det;

    vec2 step;
#ifndef PROPAGATE
    vec2 start = init_at(vec2(float(ox), float(oy)) + 0.5 * float(PATCH - 1));
    float best = cost(oy, ox, start, step, lane, base, tmpl, gx, gy);
#else
    vec2 start = prev_[i];
    float best = cost(oy, ox, start, step, lane, base, tmpl, gx, gy);
    ivec2 around[4] = ivec2[4](ivec2(-1, 0), ivec2(1, 0), ivec2(0, -1), ivec2(0, 1));
    vec2 own = start;
    for (int c = 0; c < 4; ++c) {  // every lane of the workgroup runs all four: cost() has barriers
        ivec2 q = ivec2(px, py) + around[c];
        bool inside = q.x >= 0 && q.y >= 0 && q.x < cols && q.y < rows;
        vec2 candidate = inside ? prev_[q.y * cols + q.x] : own;
        vec2 s;
        float ssd = cost(oy, ox, candidate, s, lane, base, tmpl, gx, gy);
        if (inside && ssd < best) {
            best = ssd;
            start = candidate;
            step = s;
        }
    }
#endif
    float start_ssd = best;
    vec2 u = start;
    float ssd = best;
    for (int it = 0; it < iterations; ++it) {
        u -= inverse_h * step;
        ssd = cost(oy, ox, u, step, lane, base, tmpl, gx, gy);
    }
    vec2 best_u = u;
    if (nan_bits(ssd) || nan_bits(start_ssd) || ssd > start_ssd || nonfinite_bits(u) || distance(u, start) > float(PATCH)) best_u = start;
    if (valid && lane == 0u) patch_[i] = best_u;
}
