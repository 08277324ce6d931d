// engine.geometry.seen_before on one pixel: frame n's pixel (x, y) with planar depth d, reprojected into frame
// n-k (reproject.glsl: the matrix K_prev T_prev T_n^-1 [K_n^-1 0; 0 1]), lands in front of camera n-k and
// inside its (h, w) = prev_size image.
#include "reproject.glsl"

uniform ivec2 prev_size;  // h, w of frame n-k

bool seen(int x, int y, float d) {
    float uo, vo, hz;
    if (!reproject_point(float(x) + 0.5, float(y) + 0.5, d, uo, vo, hz)) return false;
    return uo >= 0.0 && uo < float(prev_size.y) && vo >= 0.0 && vo < float(prev_size.x);
}
