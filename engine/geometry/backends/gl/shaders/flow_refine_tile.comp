// Flow refinement pass 4, tiled (flow_refine_tile): one whole red-black SOR iteration of a level in one
// dispatch, the same arithmetic as the red and the black flow_refine_sor dispatches it replaces. A workgroup
// owns a TILE x TILE tile of pixels. The red step of a pixel reads only black neighbours, unchanged during the
// red half, so the workgroup takes the red step of its tile and of a ring of one pixel around it itself (the
// ring's pixels are another tile's: computed twice, the same bits), keeps them in shared memory, and takes the
// black step of its tile from them. It reads du from inc_ and writes the new du to next_ (flow.py swaps the
// two between iterations): no workgroup reads what another writes in the same dispatch. With SYSTEM (the
// first SOR iteration of a fixed-point iteration) it also computes the system (data_system, smooth_weight: the
// flow_refine_system pass, folded in: its tile and rings from the same du) and stores its tile's in system_
// for the later iterations. The smoothness weights of the tile and two rings are loaded to shared memory
// once (an edge's weight is its left / upper pixel's).
#include "flow_refine_common.glsl"

layout(std430, binding = 13) writeonly buffer NextBuf { vec2 next_[]; };  // (H, W) du after this iteration

const int TILE = 16;          // TILE * TILE == LOCAL_SIZE: an invocation a pixel of the tile
const int RING1 = TILE + 2;   // the tile and a ring of one pixel: the red steps taken here
const int RING2 = TILE + 4;   // and of two: the smoothness weights those read

shared float ws_[RING2 * RING2];  // smoothness weight ws of the tile and two rings
shared vec2 du_[RING1 * RING1];   // du after the red half of the tile and one ring

bool in_level(int y, int x) { return y >= 0 && x >= 0 && y < size.x && x < size.y; }

// the system of pixel i: (A11, A12, A22, b1) and b2 (computed with SYSTEM, else stored by the first iteration)
vec4 system_of(int i, out float b2) {
#ifdef SYSTEM
    return data_system(i, inc_[i], b2);
#else
    b2 = system_[2 * i + 1].x;
    return system_[2 * i];
#endif
}

// the SOR step of pixel (y, x) at (ty, tx) of the tile (-1 .. TILE: the ring), its neighbours' du from inc_
// (red: they are black) or from the red half in du_ (black)
vec2 step_at(int y, int x, int ty, int tx, vec2 du, bool black) {
    int i = y * size.y + x;
    float b2;
    vec4 s0 = system_of(i, b2);
    vec2 totals[4];
    float weights[4];
    bvec4 inside;
    for (int k = 0; k < 4; ++k) {
        int ny = y + AROUND[k].y, nx = x + AROUND[k].x;
        inside[k] = in_level(ny, nx);
        int j = inside[k] ? ny * size.y + nx : i;
        vec2 dj = black ? du_[(ty + 1 + AROUND[k].y) * RING1 + tx + 1 + AROUND[k].x] : inc_[j];
        totals[k] = dense_[j] + dj;
        // right and lower edges: this pixel's weight; left and upper: the neighbour's
        int w = k % 2 == 0 ? (ty + 2) * RING2 + tx + 2 : (ty + 2 + AROUND[k].y) * RING2 + tx + 2 + AROUND[k].x;
        weights[k] = ws_[w];
    }
    return sor_step(s0, b2, dense_[i], du, totals, weights, inside);
}

void main() {
    int tiles_x = (size.y + TILE - 1) / TILE, tiles = tiles_x * ((size.x + TILE - 1) / TILE);
    int tile = int(gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x);
    if (tile >= tiles) return;  // the whole workgroup: no barrier is skipped by part of it
    int y0 = (tile / tiles_x) * TILE, x0 = (tile % tiles_x) * TILE;
    int lane = int(gl_LocalInvocationIndex);
    for (int c = lane; c < RING2 * RING2; c += LOCAL_SIZE) {
        int y = y0 - 2 + c / RING2, x = x0 - 2 + c % RING2;
        float ws = 0.0;
        if (in_level(y, x)) {
#ifdef SYSTEM
            ws = smooth_weight(y, x);
#else
            ws = system_[2 * (y * size.y + x) + 1].y;
#endif
        }
        ws_[c] = ws;
    }
    memoryBarrierShared();
    barrier();
    for (int c = lane; c < RING1 * RING1; c += LOCAL_SIZE) {  // the red half: (x + y) even
        int ty = c / RING1 - 1, tx = c % RING1 - 1, y = y0 + ty, x = x0 + tx;
        vec2 du = vec2(0.0);
        if (in_level(y, x)) {
            du = inc_[y * size.y + x];
            if (((x + y) & 1) == 0) du = step_at(y, x, ty, tx, du, false);
        }
        du_[c] = du;
    }
    memoryBarrierShared();
    barrier();
    int ty = lane / TILE, tx = lane % TILE, y = y0 + ty, x = x0 + tx;  // the black half, and the tile written
    if (!in_level(y, x)) return;
    int i = y * size.y + x;
    vec2 du = du_[(ty + 1) * RING1 + tx + 1];
    if (((x + y) & 1) == 1) du = step_at(y, x, ty, tx, du, true);
    next_[i] = du;
#ifdef SYSTEM
    float b2;
    system_[2 * i] = data_system(i, inc_[i], b2);
    system_[2 * i + 1] = vec4(b2, ws_[(ty + 2) * RING2 + tx + 2], 0.0, 0.0);
#endif
}
