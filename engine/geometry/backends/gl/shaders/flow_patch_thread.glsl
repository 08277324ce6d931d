// The inverse search of one patch on one invocation (passes flow_patch and flow_coarse; flow_patch.comp says
// what it computes): search_patch(i, propagate) is patch i's flow after one sweep.

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

vec2 search_patch(int i, bool propagate) {
    int rows = patch_count(size.x), cols = patch_count(size.y);
    int py = i / cols, px = i % cols;
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
    vec2 start;
    float best;
    if (!propagate) {
        start = init_at(vec2(float(ox), float(oy)) + 0.5 * float(PATCH - 1));
        best = cost(oy, ox, start, step);
    } else {
        start = prev_[i];
        best = cost(oy, ox, start, step);
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
    }
    float start_ssd = best;
    vec2 u = start;
    float ssd = best;
    for (int it = 0; it < iterations; ++it) {
        u -= inverse_h * step;
        ssd = cost(oy, ox, u, step);
    }
    bool worse = nan_bits(ssd) || nan_bits(start_ssd) || ssd > start_ssd;
    return worse || nonfinite_bits(u) || distance(u, start) > float(PATCH) ? start : u;
}
