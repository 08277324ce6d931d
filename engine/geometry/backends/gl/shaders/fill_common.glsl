// The hole fill's buffers (engine/geometry/holefill.py on the GPU): the warped frame and its holes in,
// per-pixel row sources, per-row flags and links, the filled colour and the packed hole mask out.

layout(std430, binding = 0) readonly buffer ColorBuf { float color_[]; };   // (H, W, 3) fallback colour
layout(std430, binding = 8) readonly buffer WarpedBuf { vec4 warped_[]; };  // (H, W) (r, g, b, depth)
layout(std430, binding = 10) readonly buffer HoleBuf { uint hole_[]; };     // (H, W) 1 = hole
layout(std430, binding = 11) buffer RowSrcBuf { int rowsrc_[]; };          // (H, W) column source, -1 none
layout(std430, binding = 12) buffer RowInfoBuf { int rowinfo_[]; };        // (H,) 1 = the row has a known pixel
layout(std430, binding = 13) buffer LinkBuf { int links_[]; };             // (H, 2) nearest such rows above, below

uniform ivec2 size;  // H, W

const float INF = uintBitsToFloat(0x7f800000u);
shared int scan_[LOCAL_SIZE];

// inclusive scan of scan_ by max (forward = from index 0 up) or min (backward = from the end down)
void scan_max_forward(uint lid) {
    for (uint off = 1u; off < uint(LOCAL_SIZE); off <<= 1) {
        int other = lid >= off ? scan_[lid - off] : -1;
        barrier();
        scan_[lid] = max(scan_[lid], other);
        barrier();
    }
}
void scan_min_backward(uint lid, int none) {
    for (uint off = 1u; off < uint(LOCAL_SIZE); off <<= 1) {
        int other = lid + off < uint(LOCAL_SIZE) ? scan_[lid + off] : none;
        barrier();
        scan_[lid] = min(scan_[lid], other);
        barrier();
    }
}
