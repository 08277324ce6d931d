// Flow pass 3, per patch of a pyramid level: DIS inverse search (Kroeger et al. 2016), the patch of the first
// image matched in the second by inverse-compositional Lucas-Kanade with mean normalisation. The template's
// gradients (central differences, centred on their patch means) give a fixed 2 x 2 Hessian (+ EPS I); each
// iteration samples the second image at x + u (bilinear), takes the mean-normalised difference e and steps
// u -= H^-1 sum(g e). The first sweep starts from the level's initial dense flow at the patch centre; with
// PROPAGATE (later sweeps) from the lowest mean-normalised SSD of the patch's own and its 4 neighbours'
// previous flows (a parallel stand-in for DIS's sequential spatial propagation). The result is the last
// iterate, or the start where that has a higher SSD or lies more than a patch away.
#include "flow_patch_common.glsl"

float tmpl[N];
float gx[N];
float gy[N];

// mean-normalised SSD of the patch at (oy, ox) moved by u, and sum(g e) into step
float cost(int oy, int ox, vec2 u, out vec2 step) {
    float e[N];
    float mean = 0.0;
    for (int k = 0; k < N; ++k) {
        vec2 p = vec2(float(ox + k % PATCH), float(oy + k / PATCH)) + u;
        e[k] = second_bilinear(p) - tmpl[k];
        mean += e[k];
    }
    mean /= float(N);
    float ssd = 0.0;
    step = vec2(0.0);
    for (int k = 0; k < N; ++k) {
        float d = e[k] - mean;
        ssd += d * d;
        step += vec2(gx[k], gy[k]) * d;
    }
    return ssd;
}

void main() {
    int rows = patch_count(size.x), cols = patch_count(size.y);
    uint i = invocation();
    if (i >= uint(rows * cols)) return;
    int py = int(i) / cols, px = int(i) % cols;
    int oy = patch_origin(py, size.x), ox = patch_origin(px, size.y);
    float mgx = 0.0, mgy = 0.0;
    for (int k = 0; k < N; ++k) {
        int y = oy + k / PATCH, x = ox + k % PATCH;
        tmpl[k] = first_at(y, x);
        gx[k] = 0.5 * (first_at(y, x + 1) - first_at(y, x - 1));
        gy[k] = 0.5 * (first_at(y + 1, x) - first_at(y - 1, x));
        mgx += gx[k];
        mgy += gy[k];
    }
    mgx /= float(N);
    mgy /= float(N);
    float hxx = EPS, hxy = 0.0, hyy = EPS;
    for (int k = 0; k < N; ++k) {
        gx[k] -= mgx;
        gy[k] -= mgy;
        hxx += gx[k] * gx[k];
        hxy += gx[k] * gy[k];
        hyy += gy[k] * gy[k];
    }
    float det = hxx * hyy - hxy * hxy;
    mat2 inverse_h = mat2(hyy, -hxy, -hxy, hxx) / det;

    vec2 step;
#ifndef PROPAGATE
    vec2 start = init_at(vec2(float(ox), float(oy)) + 0.5 * float(PATCH - 1));
    float best = cost(oy, ox, start, step);
#else
    vec2 start = prev_[i];
    float best = cost(oy, ox, start, step);
    ivec2 around[4] = ivec2[4](ivec2(-1, 0), ivec2(1, 0), ivec2(0, -1), ivec2(0, 1));
    for (int c = 0; c < 4; ++c) {
        ivec2 q = ivec2(px, py) + around[c];
        if (q.x < 0 || q.y < 0 || q.x >= cols || q.y >= rows) continue;
        vec2 candidate = prev_[q.y * cols + q.x];
        vec2 s;
        float ssd = cost(oy, ox, candidate, s);
        if (ssd < best) {
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
        ssd = cost(oy, ox, u, step);
    }
    vec2 best_u = u;
    if (nan_bits(ssd) || nan_bits(start_ssd) || ssd > start_ssd || nonfinite_bits(u) || distance(u, start) > float(PATCH)) best_u = start;
    patch_[i] = best_u;
}
