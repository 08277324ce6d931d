// Trust pass 2, per pixel: the sums over ``WINDOW`` pixels of its row (BORDER_REFLECT: ...cba|abc...) of both
// error images, in double (cv2.blur of float32 sums in double), into rows_ (H, W, 2).

layout(std430, binding = 23) readonly buffer StillBuf { float still_[]; };
layout(std430, binding = 24) readonly buffer MovedBuf { float moved_[]; };
layout(std430, binding = 25) writeonly buffer RowsBuf { dvec2 rows_[]; };

#include "trust_common.glsl"

void main() {
    uint i = invocation();
    int h = size.x, w = size.y;
    if (i >= uint(h * w)) return;
    int y = int(i) / w, x = int(i) % w;
    dvec2 sum = dvec2(0.0);
    for (int d = -WINDOW / 2; d <= WINDOW / 2; ++d) {
        int o = y * w + reflect_index(x + d, w);
        sum += dvec2(double(still_[o]), double(moved_[o]));
    }
    rows_[i] = sum;
}
