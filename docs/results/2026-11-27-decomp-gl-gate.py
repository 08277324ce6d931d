"""decomp's motion gate on the GPU (GlGate) against the CPU's (gate_boxes), on every (n-k, n) pair at k = 2 and 4
of the given rgbd-seq sequences, at the committed network's working width:

    python docs/results/2026-11-27-decomp-gl-gate.py OUT.json SEQ [SEQ ...]

Per pair: the changed pixels per tile of both (their absolute difference summed), the boxes of both, and the wall
ms of the CPU's downsampling + gate and of the GPU path (upload excluded; medians skip the first 5 pairs, which
compile). Prints the totals."""
import json, sys, time
import numpy as np
from engine import geometry
from engine.io.rgbd import read_sequence
from engine.geometry.backends import gl as glb
from engine.geometry.backends.gl.gate import GlGate
from engine.predict.decomp.gate import GateConfig, gate_boxes, boxes_from_counts, motion_residual, tile_counts
from engine.predict.decomp.network import FlowNetwork, DEFAULT_MODEL

net = FlowNetwork(DEFAULT_MODEL)
cfg = GateConfig()
gate = GlGate(cfg.color_threshold, cfg.depth_threshold, cfg.erode, cfg.unseen, cfg.tile)
warper = glb.GlFrameWarper()
rows = []
for path in sys.argv[2:]:
    seq = read_sequence(path)
    frames = [seq[i] for i in range(len(seq))]
    h, w = frames[0].depth.shape
    f = min(geometry.downsample_factor(w, net.working_width), h, w)
    images = [warper.upload(fr.color, fr.depth) for fr in frames]
    for k in (2, 4):
        for n in range(k, len(frames), k):
            a, b = frames[n - k], frames[n]
            t0 = time.perf_counter()
            low_n, low_p = geometry.downsample_frame(b.color, b.depth, b.camera.intrinsics, f), geometry.downsample_frame(a.color, a.depth, a.camera.intrinsics, f)
            boxes_cpu = gate_boxes(cfg, low_n, low_p, b.camera.world_to_camera, a.camera.world_to_camera, net.stride)
            t1 = time.perf_counter()
            counts = gate.tile_counts(images[n], images[n - k], b.camera.intrinsics, b.camera.world_to_camera,
                                      a.camera.intrinsics, a.camera.world_to_camera, f)
            boxes_gpu = boxes_from_counts(counts, low_n[1].shape, cfg.tile, cfg.tile_fraction, cfg.margin, net.stride,
                                          cfg.full_frame_fraction, cfg.min_tiles)
            t2 = time.perf_counter()
            # the CPU's counts, for the count difference
            g_n = geometry.build_mpi(low_n[0], low_n[1], 1)
            g_w, _ = geometry.forward_warp_mpi(geometry.build_mpi(low_p[0], low_p[1], 1), low_p[2], a.camera.world_to_camera, low_n[2], b.camera.world_to_camera)
            ch = motion_residual(g_n, g_w, cfg.color_threshold, cfg.depth_threshold, cfg.erode)
            ch &= geometry.seen_before(low_n[1], low_n[2], b.camera.world_to_camera, low_p[2], a.camera.world_to_camera, low_p[1].shape)
            cpu_counts = tile_counts(ch, cfg.tile)
            rows.append(dict(sequence=path.rstrip('/').split('/')[-1], k=k, n=n, factor=f, changed_cpu=int(cpu_counts.sum()),
                             count_diff=int(np.abs(cpu_counts - counts.astype(np.int64)).sum()),
                             boxes_cpu=boxes_cpu, boxes_gpu=boxes_gpu, same_boxes=boxes_cpu == boxes_gpu,
                             cpu_ms=1e3 * (t1 - t0), gpu_path_ms=1e3 * (t2 - t1)))
    print(path, sum(r['same_boxes'] for r in rows if r['sequence'] in path), flush=True)
json.dump(rows, open(sys.argv[1], 'w'), indent=1)
same = sum(r['same_boxes'] for r in rows)
print(f"pairs {len(rows)}, same boxes {same}, pairs with any count difference {sum(r['count_diff'] > 0 for r in rows)}, "
      f"max count diff {max(r['count_diff'] for r in rows)}, pixels changed (sum) {sum(r['changed_cpu'] for r in rows)}")
print("median ms cpu (downsample+gate)", np.median([r['cpu_ms'] for r in rows][5:]), "gl on llvmpipe", np.median([r['gpu_path_ms'] for r in rows][5:]))
