// A renderer's (H, W, 4) float32 output, (r, g, b linear, planar depth) per pixel, split into the backend's
// frame layout: colour (H, W, 3) and depth (H, W) (GlFrameWarper.from_rgbd; a copy, bit for bit).
layout(std430, binding = 0) readonly buffer RgbdBuf { vec4 rgbd_[]; };
layout(std430, binding = 1) writeonly buffer ColorBuf { float color_[]; };
layout(std430, binding = 2) writeonly buffer DepthBuf { float depth_[]; };

uniform uint count;  // H * W

void main() {
    uint i = invocation();
    if (i >= count) return;
    vec4 v = rgbd_[i];
    color_[3u * i] = v.r;
    color_[3u * i + 1u] = v.g;
    color_[3u * i + 2u] = v.b;
    depth_[i] = v.a;
}
