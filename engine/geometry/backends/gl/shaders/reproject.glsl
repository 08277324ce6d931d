// Eq. 6.2 on one point (engine.geometry.camera.reproject, float32 as its arithmetic): pixel coordinates (u, v)
// (centres at +0.5) with planar depth d (+inf: sky, moved by the rotation alone) through the 3x4 matrix
// K_dst T_dst T_src^-1 [K_src^-1 0; 0 1] to destination pixel coordinates (uo, vo) and homogeneous depth hz;
// false (and nothing written) behind, on or grazing the destination camera plane.
uniform vec4 row0;          // rows of the reprojection matrix, float32
uniform vec4 row1;
uniform vec4 row2;
uniform float max_coord_inv;
uniform float tiny_depth;

bool reproject_point(float u, float v, float d, out float uo, out float vo, out float hz_out) {
    bool sky = isinf(d);
    float s = sky ? 1.0 : d;
    float w = sky ? 0.0 : 1.0;
    precise float x = u * s;
    precise float y = v * s;
    precise float hu = row0.x * x + row0.y * y + row0.z * s + row0.w * w;
    precise float hv = row1.x * x + row1.y * y + row1.z * s + row1.w * w;
    precise float hz = row2.x * x + row2.y * y + row2.z * s + row2.w * w;
    precise float bound = (abs(hu) + abs(hv)) * max_coord_inv + tiny_depth;
    if (nan_bits(hz) || nan_bits(bound) || hz <= bound) return false;
    // float32's correctly rounded quotient, as numpy's: GLSL's float division may be 2.5 ulp off (NVIDIA's is;
    // at 500 px that moved coverage by 1e-4 on an H200), a double quotient rounded to float is exact
    uo = float(double(hu) / double(hz));
    vo = float(double(hv) / double(hz));
    hz_out = hz;
    return true;
}
