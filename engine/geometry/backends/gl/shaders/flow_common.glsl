// The optical flow's shared declarations (engine/geometry/backends/gl/flow.py): the two luma pyramids, each
// level of (H_l, W_l) floats (8-bit levels 0..255) stored row-major at its offset in one buffer; reads clamp
// to the level's border. Pixel (y, x) has its centre at (x + 0.5, y + 0.5); a flow u at it points to
// (x + 0.5 + u.x, y + 0.5 + u.y) in the second image, sampled bilinearly at index coordinates (x + u.x, y + u.y).
// Patches: PATCH x PATCH pixels, origins j * stride along each axis, the last one moved back to end at the
// border (origin 0 when the level is smaller than a patch: its reads clamp).
// With COARSE defined (pass flow_coarse: one workgroup runs whole levels), size and offset are variables it
// sets per level, and the work buffers are coherent and read-write (READS / WRITES: a pass's qualifiers of
// the buffers it only reads / only writes).
#ifdef COARSE
#define READS coherent
#define WRITES coherent
#else
#define READS readonly
#define WRITES writeonly
#endif

layout(std430, binding = 1) readonly buffer FirstBuf { float first_[]; };    // pyramid of the first image
layout(std430, binding = 3) readonly buffer SecondBuf { float second_[]; };  // pyramid of the second image

#ifdef COARSE
ivec2 size;
int offset;
#else
uniform ivec2 size;   // H, W of the level
uniform int offset;   // of the level in both pyramid buffers
#endif
uniform int stride;   // patch stride, pixels

float first_at(int y, int x) {
    return first_[offset + clamp(y, 0, size.x - 1) * size.y + clamp(x, 0, size.y - 1)];
}

float second_at(int y, int x) {
    return second_[offset + clamp(y, 0, size.x - 1) * size.y + clamp(x, 0, size.y - 1)];
}

// the second image at index coordinates p = (x, y), bilinear, clamped to the border
float second_bilinear(vec2 p) {
    p = clamp(p, vec2(0.0), vec2(float(size.y - 1), float(size.x - 1)));
    vec2 f = floor(p);
    vec2 t = p - f;
    int x = int(f.x), y = int(f.y);
    float top = mix(second_at(y, x), second_at(y, x + 1), t.x);
    float bottom = mix(second_at(y + 1, x), second_at(y + 1, x + 1), t.x);
    return mix(top, bottom, t.y);
}

// patches along an axis of n pixels
int patch_count(int n) {
    return n <= PATCH ? 1 : (n - PATCH + stride - 1) / stride + 1;
}

// first pixel of patch j along an axis of n pixels
int patch_origin(int j, int n) {
    return max(0, min(j * stride, n - PATCH));
}
