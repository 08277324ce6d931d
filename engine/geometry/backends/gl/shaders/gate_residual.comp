// Motion gate pass 2 (engine.predict.decomp.gate.motion_residual), per pixel of the working resolution: 1 where
// the camera-compensated frame n-k (the FRAME splat's warped_ and hole_) covers the pixel and still differs
// from frame n: encoded colour (sqrt(c / (1 + c) + 1e-4) - 0.01, c clipped at 0; max over RGB) by more than
// color_threshold, or inverse depth by more than depth_threshold relative to the one-plane MPI's depth (the
// plane halfway in inverse depth between frame n's smallest and largest finite depth, float32, as
// engine.geometry.plane_depths makes it; 1 when frame n has no finite depth). numpy's float32 arithmetic:
// quotients and square roots in double, rounded to float (correctly rounded, as numpy's); d_depth in double.
layout(std430, binding = 20) readonly buffer LowColorBuf { float low_color_[]; };  // frame n (h, w, 3)
layout(std430, binding = 21) readonly buffer LowDepthBuf { float low_depth_[]; };  // frame n (h, w)
layout(std430, binding = 22) readonly buffer RangeBuf { uint range_[]; };          // bits of (min, max)
layout(std430, binding = 8) readonly buffer WarpedBuf { vec4 warped_[]; };         // frame n-k warped
layout(std430, binding = 10) readonly buffer HoleBuf { uint hole_[]; };
layout(std430, binding = 23) writeonly buffer ChangedBuf { uint changed_[]; };     // (h, w) 0 / 1

uniform ivec2 size;             // (h, w)
uniform float color_threshold;  // float32
uniform uvec2 depth_threshold;  // the float64 threshold's bits (low word, high word)

float encode(float c) {
    c = max(c, 0.0);
    precise float one_plus = 1.0 + c;
    precise float q = float(double(c) / double(one_plus)) + 1.0e-4;
    precise float e = float(sqrt(double(q))) - 0.01;
    return e;
}

float inverse_depth(float d) {
    return nonfinite_bits(d) ? 0.0 : float(1.0LF / double(max(d, 1.0e-30)));
}

double reference_depth() {
    if (range_[0] == 0xFFFFFFFFu) return 1.0LF;  // no finite depth: planes at +inf
    double near = double(uintBitsToFloat(range_[0])), far = double(uintBitsToFloat(range_[1]));
    double plane = double(float(1.0LF / (0.5LF / near + 0.5LF / far)));
    return 2.0LF / (1.0LF / plane + 1.0LF / plane);
}

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    uint changed = 0u;
    if (hole_[i] == 0u) {
        vec4 w = warped_[i];
        float d_color = 0.0;
        for (int c = 0; c < 3; ++c) {
            d_color = max(d_color, abs(encode(low_color_[3u * i + uint(c)]) - encode(w[c])));
        }
        precise float diff = inverse_depth(low_depth_[i]) - inverse_depth(w.w);
        double d_depth = double(abs(diff)) * reference_depth();
        double threshold = packDouble2x32(depth_threshold);
        if (d_color > color_threshold || d_depth > threshold) changed = 1u;
    }
    changed_[i] = changed;
}
