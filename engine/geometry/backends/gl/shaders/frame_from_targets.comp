// A raster renderer's render targets, as GL draws them (row 0 at the bottom), taken into the backend's frame
// layout (rows top to bottom): rgbd_target (r, g, b linear, planar depth; depth 0: no surface) becomes colour
// (H, W, 3) and depth (H, W) with +inf where there is no surface; motion_target (x, y, has, -) becomes the
// motion vectors (H, W, 2) in pixels, NaN where `has` is 0 (engine.scenegen.live: a copy, bit for bit).
uniform sampler2D rgbd_target;
uniform sampler2D motion_target;
layout(std430, binding = 0) writeonly buffer ColorBuf { float color_[]; };
layout(std430, binding = 1) writeonly buffer DepthBuf { float depth_[]; };
layout(std430, binding = 2) writeonly buffer VectorBuf { float vectors_[]; };

uniform ivec2 size;  // (H, W)

void main() {
    uint i = invocation();
    uint w = uint(size.y);
    if (i >= uint(size.x) * w) return;
    ivec2 texel = ivec2(int(i % w), size.x - 1 - int(i / w));
    vec4 rgbd = texelFetch(rgbd_target, texel, 0);
    vec4 motion = texelFetch(motion_target, texel, 0);
    color_[3u * i] = rgbd.r;
    color_[3u * i + 1u] = rgbd.g;
    color_[3u * i + 2u] = rgbd.b;
    depth_[i] = rgbd.a > 0.0 ? rgbd.a : uintBitsToFloat(0x7f800000u);
    bool has = motion.z > 0.0;
    vectors_[2u * i] = has ? motion.x : uintBitsToFloat(0x7fc00000u);
    vectors_[2u * i + 1u] = has ? motion.y : uintBitsToFloat(0x7fc00000u);
}
