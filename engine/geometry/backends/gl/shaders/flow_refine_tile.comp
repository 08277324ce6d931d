// Flow refinement pass 4, tiled (flow_refine_tile): STEPS whole red-black SOR iterations of a level in one
// dispatch, the same arithmetic as the 2 STEPS red and black flow_refine_sor dispatches it replaces. A
// workgroup owns a TILE x TILE tile of pixels and takes the steps in shared memory. A half-step of one colour
// reads only the other colour's du, so the steps of the tile need those of a ring of pixels around it one
// wider per half-step before: the workgroup loads du and the smoothness weights of the tile and 2 STEPS rings
// (the ring pixels are other tiles': their steps are taken twice, the same bits), then takes the 2 STEPS
// half-steps, red ((x + y) even) first, each on a region one ring smaller, a barrier after each, and writes
// its tile's du. It reads du from inc_ and writes the new du to next_ (flow.py swaps the two between
// dispatches): no workgroup reads what another writes in the same dispatch. With SYSTEM (the first dispatch of
// a fixed-point iteration) it computes the system (data_system, smooth_weight: the flow_refine_system pass
// folded in, from the same du) and stores its tile's in system_ for the later dispatches.
#include "flow_refine_common.glsl"

layout(std430, binding = 13) writeonly buffer NextBuf { vec2 next_[]; };  // (H, W) du after these iterations

// STEPS (defined by flow.py, 1 .. SOR_STEPS there): the SOR iterations of a dispatch
const int TILE = 16;                   // TILE * TILE == LOCAL_SIZE: an invocation a pixel of the tile
const int HALO = 2 * STEPS;            // rings loaded around the tile
const int SIDE = TILE + 2 * HALO;      // du and smoothness weights: the tile and HALO rings
const int INNER = SIDE - 2;            // systems: the tile and HALO - 1 rings (the pixels that take steps)

shared vec2 du_[SIDE * SIDE];
shared float ws_[SIDE * SIDE];         // smoothness weight of a pixel's right and lower edges
shared vec4 a_[INNER * INNER];         // (A11, A12, A22, b1)
shared float b2_[INNER * INNER];

bool in_level(int y, int x) { return y >= 0 && x >= 0 && y < size.x && x < size.y; }

void sync_shared() {
    memoryBarrierShared();
    barrier();
}

void main() {
    int tiles_x = (size.y + TILE - 1) / TILE, tiles = tiles_x * ((size.x + TILE - 1) / TILE);
    int tile = int(gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x);
    if (tile >= tiles) return;  // the whole workgroup: no barrier is skipped by part of it
    int y0 = (tile / tiles_x) * TILE - HALO, x0 = (tile % tiles_x) * TILE - HALO;  // the region's first pixel
    int lane = int(gl_LocalInvocationIndex);
    for (int c = lane; c < SIDE * SIDE; c += LOCAL_SIZE) {
        int y = y0 + c / SIDE, x = x0 + c % SIDE;
        vec2 du = vec2(0.0);
        float ws = 0.0;
        if (in_level(y, x)) {
            int i = y * size.y + x;
            du = inc_[i];
#ifdef SYSTEM
            ws = smooth_weight(y, x);
#else
            ws = system_[2 * i + 1].y;
#endif
        }
        du_[c] = du;
        ws_[c] = ws;
    }
    for (int c = lane; c < INNER * INNER; c += LOCAL_SIZE) {
        int y = y0 + 1 + c / INNER, x = x0 + 1 + c % INNER;
        vec4 a = vec4(0.0);
        float b2 = 0.0;
        if (in_level(y, x)) {
            int i = y * size.y + x;
#ifdef SYSTEM
            a = data_system(i, inc_[i], b2);
#else
            a = system_[2 * i];
            b2 = system_[2 * i + 1].x;
#endif
        }
        a_[c] = a;
        b2_[c] = b2;
    }
    sync_shared();
    for (int h = 0; h < 2 * STEPS; ++h) {
        int ring = HALO - 1 - h;            // this half-step updates the tile and `ring` rings
        int side = TILE + 2 * ring, first = HALO - ring;
        for (int c = lane; c < side * side; c += LOCAL_SIZE) {
            int ry = first + c / side, rx = first + c % side, y = y0 + ry, x = x0 + rx;
            if (!in_level(y, x) || ((x + y) & 1) != (h & 1)) continue;
            int cell = ry * SIDE + rx, s = (ry - 1) * INNER + rx - 1;
            vec2 totals[4];
            float weights[4];
            bvec4 inside;
            for (int k = 0; k < 4; ++k) {
                int ny = y + AROUND[k].y, nx = x + AROUND[k].x;
                int neighbour = cell + AROUND[k].y * SIDE + AROUND[k].x;
                inside[k] = in_level(ny, nx);
                totals[k] = dense_[inside[k] ? ny * size.y + nx : y * size.y + x] + du_[neighbour];
                weights[k] = ws_[k % 2 == 0 ? cell : neighbour];  // right / lower edge: this pixel's weight
            }
            du_[cell] = sor_step(a_[s], b2_[s], dense_[y * size.y + x], du_[cell], totals, weights, inside);
        }
        sync_shared();
    }
    int ry = HALO + lane / TILE, rx = HALO + lane % TILE, y = y0 + ry, x = x0 + rx;
    if (!in_level(y, x)) return;
    int i = y * size.y + x, cell = ry * SIDE + rx;
    next_[i] = du_[cell];
#ifdef SYSTEM
    int s = (ry - 1) * INNER + rx - 1;
    system_[2 * i] = a_[s];
    system_[2 * i + 1] = vec4(b2_[s], ws_[cell], 0.0, 0.0);
#endif
}
