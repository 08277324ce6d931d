// Trust pass 1, per pixel of frame n: the photometric errors engine.predict.dis.confident_motion averages:
// still_ = |luma_n - target| (no object motion), moved_ = |luma_n - target sampled at the pixel moved by the
// flow u(n -> n-k)| (OpenCV 5's remap, INTER_LINEAR, float maps: the exact fraction, linear along x then y
// by fused multiply-adds, taps outside the image read -1; a sample below 0 costs 255). Positions are pixel
// indices (x, y) + (du, dv), as engine.predict.dis.warp_error samples.

layout(std430, binding = 20) readonly buffer LumaNBuf { float luma_n_[]; };   // (H, W) 8-bit levels
layout(std430, binding = 21) readonly buffer TargetBuf { float target_[]; };  // (H, W) 8-bit levels
layout(std430, binding = 22) readonly buffer FlowBuf { vec2 flow_[]; };       // (H, W) u(n -> n-k) pixels
layout(std430, binding = 23) writeonly buffer StillBuf { float still_[]; };   // (H, W)
layout(std430, binding = 24) writeonly buffer MovedBuf { float moved_[]; };   // (H, W)

uniform ivec2 size;  // H, W

float tap(int x, int y) {
    return (x >= 0 && x < size.y && y >= 0 && y < size.x) ? target_[y * size.y + x] : -1.0;
}

void main() {
    uint i = invocation();
    int h = size.x, w = size.y;
    if (i >= uint(h * w)) return;
    int y = int(i) / w, x = int(i) % w;
    float luma = luma_n_[i];
    still_[i] = abs(luma - target_[i]);
    vec2 f = flow_[i];
    precise float px = float(x) + f.x;
    precise float py = float(y) + f.y;
    float fx = floor(px), fy = floor(py);
    int sx = int(fx), sy = int(fy);
    precise float ax = px - fx;
    precise float ay = py - fy;
    float sampled;
    if (sx >= w || sx + 1 < 0 || sy >= h || sy + 1 < 0) {
        sampled = -1.0;
    } else {  // along x then y by fused multiply-adds: OpenCV 5's float32 result to the bit
              // (docs/results/2026-11-27-flow2d-prep-cost-remap.py)
        float t00 = tap(sx, sy), t01 = tap(sx + 1, sy), t10 = tap(sx, sy + 1), t11 = tap(sx + 1, sy + 1);
        precise float top = fma(t01 - t00, ax, t00);
        precise float bottom = fma(t11 - t10, ax, t10);
        precise float s = fma(bottom - top, ay, top);
        sampled = s;
    }
    moved_[i] = sampled < 0.0 ? 255.0 : abs(luma - sampled);
}
