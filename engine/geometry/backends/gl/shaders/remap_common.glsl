// OpenCV 5's remap of the 8-bit luma target_ (declared by the including pass: (frame.x, frame.y) = (H, W)
// floats), INTER_LINEAR with float maps, BORDER_CONSTANT -1: the exact fraction, linear along x then y by
// fused multiply-adds, taps outside the image read -1 (OpenCV's float32 result to the bit:
// docs/results/2026-11-27-flow2d-prep-cost-remap.py). Positions are pixel indices (x, y) + flow, as
// engine.predict.dis.warp_error samples.

float remap_tap(int x, int y, ivec2 frame) {
    return (x >= 0 && x < frame.y && y >= 0 && y < frame.x) ? target_[y * frame.y + x] : -1.0;
}

// the target at pixel (x, y) moved by f, -1 where all four taps lie outside
float remap_linear(int x, int y, vec2 f, ivec2 frame) {
    precise float px = float(x) + f.x;
    precise float py = float(y) + f.y;
    float fx = floor(px), fy = floor(py);
    int sx = int(fx), sy = int(fy);
    precise float ax = px - fx;
    precise float ay = py - fy;
    if (sx >= frame.y || sx + 1 < 0 || sy >= frame.x || sy + 1 < 0) return -1.0;
    float t00 = remap_tap(sx, sy, frame), t01 = remap_tap(sx + 1, sy, frame);
    float t10 = remap_tap(sx, sy + 1, frame), t11 = remap_tap(sx + 1, sy + 1, frame);
    precise float top = fma(t01 - t00, ax, t00);
    precise float bottom = fma(t11 - t10, ax, t10);
    precise float s = fma(bottom - top, ay, top);
    return s;
}

// engine.predict.dis.warp_error before its window mean: |luma - the target sampled at x + f|, 255 below 0
float remap_error(float luma, int x, int y, vec2 f, ivec2 frame) {
    float sampled = remap_linear(x, y, f, frame);
    return sampled < 0.0 ? 255.0 : abs(luma - sampled);
}
