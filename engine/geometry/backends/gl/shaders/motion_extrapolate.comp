// The object flow of the moving pixels of a frame from their 3D motion (engine.geometry.kernels.extrapolate_points):
// P' = P + s V + s (s + 1) / 2 A in the frame's camera axes, flow = (project(P') - pixel centre, z' - z), NaN
// where P' reaches the camera plane (the splat drops it). float64 as the CPU kernel. Pixels not listed keep
// the zero the flow buffer was cleared to.

layout(std430, binding = 1) readonly buffer DepthBuf { float depth_[]; };       // (H, W)
layout(std430, binding = 3) writeonly buffer FlowBuf { float flow_[]; };        // (H, W, 3)
layout(std430, binding = 16) readonly buffer MovingBuf { uint moving_[]; };     // (M,) flat pixel indices
layout(std430, binding = 17) readonly buffer VelocityBuf { float velocity_[]; }; // (M, 3)
layout(std430, binding = 18) readonly buffer AccelBuf { float accel_[]; };      // (M, 3) when has_acceleration

uniform int num_moving;
uniform int width;
uniform int has_acceleration;
uniform double step;
uniform dvec3 k_row0;      // K's rows (k10 = 0)
uniform dvec2 k_row1;      // (k11, k12)
uniform dvec3 kinv_row0;
uniform dvec2 kinv_row1;   // (kinv11, kinv12)

void main() {
    uint i = invocation();
    if (i >= uint(num_moving)) return;
    uint pix = moving_[i];
    int y = int(pix) / width, x = int(pix) % width;
    double u = double(x) + 0.5LF, v = double(y) + 0.5LF;
    double z = double(depth_[pix]);
    double px = z * (kinv_row0.x * u + kinv_row0.y * v + kinv_row0.z);
    double py = z * (kinv_row1.x * v + kinv_row1.y);
    double half_s = 0.5LF * step * (step + 1.0LF);
    dvec3 m = step * dvec3(velocity_[3u * i], velocity_[3u * i + 1u], velocity_[3u * i + 2u]);
    if (has_acceleration != 0) {
        m += half_s * dvec3(accel_[3u * i], accel_[3u * i + 1u], accel_[3u * i + 2u]);
    }
    double nx = px + m.x, ny = py + m.y, nz = z + m.z;
    vec3 f;
    if (nz > 1e-6LF * z) {
        f = vec3(float((k_row0.x * nx + k_row0.y * ny) / nz + k_row0.z - u), float(k_row1.x * ny / nz + k_row1.y - v),
                 float(nz - z));
    } else {
        f = vec3(uintBitsToFloat(0x7fc00000u));
    }
    flow_[3u * pix] = f.x;
    flow_[3u * pix + 1u] = f.y;
    flow_[3u * pix + 2u] = f.z;
}
