// DIS densification of one pixel (passes flow_densify and flow_coarse; needs patch_, the level's patch flows):
// the average of the flows of the patches that cover pixel (y, x) weighted by 1 / max(1, |second(x + u) -
// first(x)|) (8-bit levels): a patch flow that does not explain the pixel counts little; 0 where none covers it.

vec2 densify_at(int y, int x) {
    int rows = patch_count(size.x), cols = patch_count(size.y);
    float value = first_at(y, x);
    vec2 sum = vec2(0.0);
    float weight = 0.0;
    for (int py = max(0, (y - PATCH) / stride); py <= min(rows - 1, y / stride + 1); ++py) {
        int oy = patch_origin(py, size.x);
        if (y < oy || y >= oy + PATCH) continue;
        for (int px = max(0, (x - PATCH) / stride); px <= min(cols - 1, x / stride + 1); ++px) {
            int ox = patch_origin(px, size.y);
            if (x < ox || x >= ox + PATCH) continue;
            vec2 u = patch_[py * cols + px];
            float w = 1.0 / max(1.0, abs(second_bilinear(vec2(float(x), float(y)) + u) - value));
            sum += w * u;
            weight += w;
        }
    }
    return weight > 0.0 ? sum / weight : vec2(0.0);
}
