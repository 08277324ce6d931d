// Flow refinement pass 2, per pixel of a level: the derivatives of the refinement's energy, Sobel size 1 with
// replicated borders: Ix, Iy of the mean image, Ixx, Ixy of Ix, Iyy of Iy, Ixz, Iyz of Iz.
#include "flow_refine_common.glsl"

float mean_at(int y, int x) { return avg_[pixel(y, x)].x; }
float ix_at(int y, int x) {
    y = clamp(y, 0, size.x - 1);
    x = clamp(x, 0, size.y - 1);
    return mean_at(y, x + 1) - mean_at(y, x - 1);
}
float iy_at(int y, int x) {
    y = clamp(y, 0, size.x - 1);
    x = clamp(x, 0, size.y - 1);
    return mean_at(y + 1, x) - mean_at(y - 1, x);
}

void main() {
    uint i = invocation();
    if (i >= uint(size.x * size.y)) return;
    int y = int(i) / size.y, x = int(i) % size.y;
    float iz = avg_[i].y;
    deriv_[2u * i] = vec4(ix_at(y, x), iy_at(y, x), iz, ix_at(y, x + 1) - ix_at(y, x - 1));
    deriv_[2u * i + 1u] = vec4(ix_at(y + 1, x) - ix_at(y - 1, x), iy_at(y + 1, x) - iy_at(y - 1, x),
                               avg_[pixel(y, x + 1)].y - avg_[pixel(y, x - 1)].y,
                               avg_[pixel(y + 1, x)].y - avg_[pixel(y - 1, x)].y);
}
