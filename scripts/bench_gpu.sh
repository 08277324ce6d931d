#!/usr/bin/env bash
# The GPU checks in one go, for a machine with a hardware OpenGL 4.3 context (EGL) and torch with CUDA:
#   bash scripts/bench_gpu.sh OUT_DIR          (PYTHON=... picks the interpreter, default python3;
#                                               ONLY="gl_tests backends" runs just the steps named)
#   SET=realtime bash scripts/bench_gpu.sh OUT_DIR   the real-time check alone, at most 5 minutes: the live loop's
#       and the splats' tests, cpu and gl side by side at RT_SIZES' first size, the GL splats (binned, atomic) side
#       by side on the frame path at every RT_SIZES size (tools.bench_gl_warp: GPU ms per stage and pass),
#       `interleave play --headless` on the gl path (live renderer, frames kept on the GPU and drawn from
#       textures) for every RT_SIZES size at k = 2 and k = 4, and a table: GPU ms per stage, wall ms, rendered /
#       generated / shown fps (realtime.json beside it).
#       RT_SIZES (default "1920x1080 3840x2160") and RT_FRAMES (ticks per play run, default 120) make a small
#       run on a software renderer, e.g. RT_SIZES=320x180 RT_FRAMES=12 (GPU ms are not timed there).
# 0. the real-time steps (SET=realtime, above);
# 1. the GL passes' tests against their CPU references, on the GPU's driver;
# 2. tools.bench_backends: cpu and gl side by side, 640x360 to 3840x2160, with GPU ms per stage (and at
#    1920x1080 with 8-bit sRGB frames in and out);
#    tools.profile_gl_passes: GPU ms per compute pass at 1920x1080;
#    tools.profile_gl_flow: the GPU's flow alone, its dispatches and GPU ms per stage and pass, the passes as they
#    were beside the defaults, back to back and with idle gaps;
# 3. tools.bench_torch_networks: the engine's networks in torch, CPU and CUDA (onnxruntime-gpu stands in);
#    tools.bench_net_runner: the exported graphs in the engine's torch runner on CUDA against onnxruntime on the
#    CPU, and flow2d[estimator=corr] and decomp at 1920x1080 with their networks on CUDA and on the CPU;
# 4. a static field: a generated 3-view forward-facing capture at 504x378 trained by the default command on
#    CUDA, exported, and its GL renderer timed (tools.bench_fields) at 512x512, 960x540 and 1920x1080; the same
#    capture trained with deferred shading, exported with its baked form, and the baked GL renderer timed beside
#    the exact one at 960x540 and 1920x1080, and the same for lego trained with the deferred recipe (LEGO_DIR)
#    and for D-NeRF lego's dynamic field trained to bake (DNERF_DIR).
#   SET=fields bash scripts/bench_gpu.sh OUT_DIR   the fields alone, about 8 minutes on an H200 (2026-11-30): the
#       static default command timed on CUDA, the deferred field's baked GL renderer at 960x540 and 1920x1080 (ms
#       with the readback, and without it: back to back, dispatch to finish), the dynamic default against K-Planes
#       on CUDA (issues 44, 45; docs/results/2026-11-30-gpu-h200-fields.md);
#   SET=corrflow bash scripts/bench_gpu.sh OUT_DIR   (issue 43) the correlation flow network trained on CUDA: the
#       training scenes rendered and their pairs built (CF_WORKERS processes), CF_STEPS steps (default 3000) of a
#       network of CF_CHANNELS widths (default the committed 16,32,64,64,32,48; started from the committed weights when
#       the widths are theirs) with CF_ITERATIONS (6) supervised iterations, batch CF_BATCH (16), exported at 2 and 4
#       iterations into OUT_DIR, and the EPE of `corr` on the validation sequences against the committed network's
#       (corrflow_val.json). Calibrate with a small CF_STEPS first: render + pairs ~4 min on 14 processes (estimate).
# Each step has a time limit and its output goes to OUT_DIR/run.log; JSON results beside it (15 files with the
# lego data, 17 with the D-NeRF data too) and the GPU's clocks during the run (clocks.csv).
set -uo pipefail
out="${1:?usage: bash scripts/bench_gpu.sh OUT_DIR}"
py="${PYTHON:-python3}"
work="${TMPDIR:-/tmp}/interleave_bench_gpu"
mkdir -p "$out" "$work"
log="$out/run.log"
rt_sizes="${RT_SIZES:-1920x1080 3840x2160}"
rt_frames="${RT_FRAMES:-120}"
if [ "${SET:-}" = corrflow ] && [ -z "${ONLY:-}" ]; then
    ONLY="cf_pairs cf_train cf_export cf_val"
fi
if [ "${SET:-}" = fields ] && [ -z "${ONLY:-}" ]; then
    ONLY="gl_context field_capture field_train field_train_deferred field_export_deferred field_render_baked dyn_rig"
    ONLY="$ONLY dyn_derf dyn_kplanes"
fi
if [ "${SET:-}" = realtime ] && [ -z "${ONLY:-}" ]; then
    ONLY="gl_context rt_tests rt_backends rt_warp"
    for size in $rt_sizes; do ONLY="$ONLY play_${size}_k2 play_${size}_k4"; done
    ONLY="$ONLY rt_summary"
fi
step() {  # step NAME SECONDS COMMAND...
    local name=$1 limit=$2
    shift 2
    if [ -n "${ONLY:-}" ] && [[ " $ONLY " != *" $name "* ]]; then return; fi
    echo "== $name: $* ($(date +%T))" | tee -a "$log"
    timeout "$limit" "$@" >>"$log" 2>&1
    echo "== $name: exit $? ($(date +%T))" | tee -a "$log"
}
{ nvidia-smi -L; "$py" --version; } >>"$log" 2>&1 || true
# the GPU's clocks every 100 ms while the steps run: a GPU left idle between frames drops to low clocks,
# which a timer query then counts (a candidate for the GL flow's 74 ms on the H200 against 15 ms alone)
nvidia-smi --query-gpu=timestamp,clocks.sm,clocks.mem,power.draw,utilization.gpu --format=csv -lms 100 \
    >"$out/clocks.csv" 2>/dev/null &
clocks=$!
trap 'kill $clocks 2>/dev/null' EXIT
step gl_context 30 "$py" -c "from engine.geometry.backends import gl_renderer; print(gl_renderer())"
# the real-time path: the live renderer, textures, play's gl path and both splats held to their references on
# this driver, reproject and mvec with the float32 readback (cpu beside gl), the two splats side by side, then the
# live loop headless at each size
step rt_tests 90 "$py" -m pytest -q -p no:cacheprovider tests/scenegen/test_live.py tests/predict/test_gl_texture.py \
    tests/demos/test_play_gl.py tests/geometry/test_gl_splat.py \
    tests/geometry/test_gl_frame.py::test_the_binned_and_atomic_splats_warp_a_frame_to_the_same_bits
rt_first="${rt_sizes%% *}"
step rt_backends 90 "$py" -m tools.bench_backends --sizes "$rt_first" --repeats 1 --frames 4 \
    --methods "reproject,mvec" --out "$work/scenes" --json "$out/rt_backends.json"
step rt_warp 60 "$py" -m tools.bench_gl_warp --sizes "${rt_sizes// /,}" --repeats 20 --frames 4 --out "$work/scenes" \
    --json "$out/rt_warp.json"
for size in $rt_sizes; do
    for k in 2 4; do
        step "play_${size}_k${k}" 60 "$py" -m engine.cli play --headless --backend gl --method mvec --renderer live \
            --width "${size%x*}" --height "${size#*x}" --k "$k" --frames "$rt_frames" --loop 240 \
            --json "$out/play_${size}_k${k}.json"
    done
done
step rt_summary 30 "$py" - "$out" $rt_sizes <<'PY'
import json, sys
from pathlib import Path
out, sizes = Path(sys.argv[1]), sys.argv[2:]
runs, lines = {}, [f"{'play (gl, live renderer, textures)':<36} {'rendered':>9} {'generated':>10} {'shown':>7} fps   "
                   f"wall ms: render / generate / prepare   GPU ms per stage (median)"]
for size in sizes:
    for k in (2, 4):
        path = out / f"play_{size}_k{k}.json"
        if not path.exists():
            lines.append(f"{size} k={k}: no result ({path.name} missing: see run.log)")
            continue
        s = runs[f"{size}_k{k}"] = json.loads(path.read_text())
        software = any(name in s["device"].lower() for name in ("llvmpipe", "softpipe", "swrast", "software"))
        gpu = " ".join(f"{n} {v:.2f}" for n, v in s["gpu_ms"].items()) or "-"
        gpu = f"- (software renderer {s['device']!r}: no GPU timed)" if software else gpu
        lines.append(f"{size} k={k} {s['method']:<22} {s['rendered_fps']:>9.1f} {s['generated_fps']:>10.1f} "
                     f"{s['shown_fps']:>7.1f}       {s['render_ms']:.2f} / {s['generate_ms']:.2f} / "
                     f"{s['prepare_ms']:.2f}   {gpu}")
backends = out / "rt_backends.json"
if backends.exists():
    runs["backends_with_readback"] = json.loads(backends.read_text())
warp = out / "rt_warp.json"
if warp.exists():  # the splats side by side on the frame path (tools.bench_gl_warp)
    doc = runs["splats"] = json.loads(warp.read_text())
    for r in doc["runs"]:
        stages = " ".join(f"{n} {v:.3f}" for n, v in r["gpu_stage_ms"].items()) if doc["hardware"] else "-"
        lines.append(f"splat {r['splat']:<7} {r['size'][0]}x{r['size'][1]} {r['case']:<12} GPU ms: {stages}   "
                     f"wall ms: splat {r['splat_wall_ms']:.2f}, warp + fill {r['wall_ms']:.2f}   "
                     f"work MB {sum(r['work_bytes'].values()) / 1e6:.1f}   diff {r['max_diff_from_atomic']:.1e}")
lines.append("fps: 1000 / median wall ms (rendered: draw + depth and vectors read back; generated: the predictor's "
             "render, left on the GPU); shown: ticks per second of the whole loop, glFinish each tick; the backends "
             "with the float32 readback: rt_backends.json, run.log")
(out / "realtime.json").write_text(json.dumps(runs, indent=2) + "\n")
(out / "realtime.txt").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
PY
if [[ -z "${ONLY:-}" || " $ONLY " == *" rt_summary "* ]]; then  # the table on the terminal too
    cat "$out/realtime.txt" 2>/dev/null
fi
step gl_tests 120 "$py" -m pytest -q -p no:cacheprovider tests/geometry/test_gl_flow.py tests/geometry/test_gl_frame.py \
    tests/geometry/test_gl_splat.py tests/geometry/test_gl_trust.py tests/predict/test_gl_backend.py \
    tests/predict/test_gl_refine.py tests/predict/test_gl_gate.py tests/tools/test_bench_backends.py \
    tests/fields/test_glfield.py tests/fields/test_dynrender.py tests/runtime/test_session.py tests/runtime/test_server.py
step backends 180 "$py" -m tools.bench_backends --sizes 640x360,960x540,1920x1080 --repeats 2 \
    --methods "reproject,mvec,flow2d,flow2d[estimator=gl],flow2d[estimator=corr],decomp,decomp[estimator=gl]" \
    --out "$work/scenes" --json "$out/backends.json"
# at 4K the CPU side of every method on the cpu backend takes seconds a frame: one pass; decomp with the GPU's
# estimator (its full-resolution stages on the GPU) for the 4K target, not decomp with DIS
step backends_4k 200 "$py" -m tools.bench_backends --sizes 3840x2160 --repeats 1 --frames 4 \
    --methods "reproject,mvec,flow2d[estimator=gl],decomp[estimator=gl]" --out "$work/scenes" \
    --json "$out/backends_4k.json"
# 8-bit frames in and out (a Session's color_in/color_out="srgb8"): gl uploads the codes and decodes them on
# the GPU, encodes the prediction there and reads back 3 bytes a pixel instead of 12
step backends_srgb8 120 "$py" -m tools.bench_backends --sizes 1920x1080 --repeats 2 --methods "reproject,mvec" \
    --encoding srgb8 --out "$work/scenes" --json "$out/backends_srgb8.json"
step passes 150 "$py" -m tools.profile_gl_passes --size 1920x1080 --methods "reproject,mvec,flow2d[estimator=gl],decomp[estimator=gl]" \
    --out "$work/scenes" --json "$out/passes.json"
# the GPU's flow alone (FLOW_SIZES, default "960x540 1920x1080"; e.g. FLOW_SIZES=160x96 on a software renderer):
# dispatches and GPU ms per stage of the passes as they were (every level by its passes, SOR as red and black
# dispatches), the one-invocation search and the defaults (flow_coarse, flow_refine_tile), back to back with GPU ms
# per pass, then with 50 ms of idle GPU before each estimate
flow_sizes="${FLOW_SIZES:-960x540 1920x1080}"
flow_sizes="${flow_sizes// /,}"
step flow_search 150 "$py" -m tools.profile_gl_flow --sizes "$flow_sizes" --repeats 5 --passes \
    --out "$work/scenes" --json "$out/flow_search.json"
step flow_search_idle 120 "$py" -m tools.profile_gl_flow --sizes "${flow_sizes##*,}" --repeats 3 --idle 0.05 \
    --out "$work/scenes" --json "$out/flow_search_idle.json"
step networks 60 "$py" -m tools.bench_torch_networks --json "$out/networks.json"
# the exported graphs as the engine runs them without onnxruntime-gpu: torch on CUDA (engine.predict.torch_onnx)
# beside onnxruntime on the CPU, then the no-vector methods whose networks take that path, on the gl backend,
# with the networks on the GPU (INTERLEAVE_ORT_DEVICE=cuda) and on the CPU (cpu); needs the onnx wheel
step net_runner 120 "$py" -m tools.bench_net_runner --devices cuda --json "$out/net_runner.json"
for device in cuda cpu; do
    INTERLEAVE_ORT_DEVICE=$device step "net_methods_$device" 150 "$py" -m tools.bench_backends --sizes 1920x1080 \
        --methods "reproject,flow2d[estimator=corr],decomp" --repeats 1 --frames 4 --out "$work/scenes" \
        --json "$out/net_methods_$device.json"
done
step field_capture 30 "$py" -m engine.cli render-rig "$work/rig" --seed 7 --width 504 --height 378 --static \
    --num-cameras 8 --test-cameras 2 --baseline 0.25
step field_train 150 "$py" -m engine.cli train field --scene "$work/rig" --train-views cam1,cam3,cam6 \
    --test-views cam2,cam5 --device cuda --out "$work/field"
cp "$work/field/scores.json" "$out/field_scores.json" 2>/dev/null
step field_export 60 "$py" -m engine.cli export field "$work/field"
step field_render 60 "$py" -m tools.bench_fields static "$work/field/export" --run "$work/field" --sizes 512x512 \
    --skip numpy,onnx --json "$out/field_render.json"
step field_render_hd 60 "$py" -m tools.bench_fields static "$work/field/export" --run "$work/field" \
    --sizes 960x540,1920x1080 --skip numpy,onnx,torch --json "$out/field_render_hd.json"
# the same capture trained with deferred shading, exported with its baked form (engine.fields.glbaked): the baked
# renderer beside the exact one at 960x540 and 1920x1080 (its PSNR against the exact GL render of the same field)
step field_train_deferred 150 "$py" -m engine.cli train field --scene "$work/rig" --train-views cam1,cam3,cam6 \
    --test-views cam2,cam5 --device cuda --field.shading deferred --out "$work/field_deferred"
cp "$work/field_deferred/scores.json" "$out/field_deferred_scores.json" 2>/dev/null
step field_export_deferred 180 "$py" -m engine.cli export field "$work/field_deferred"
step field_render_baked 90 "$py" -m tools.bench_fields static "$work/field_deferred/export" --run "$work/field_deferred" \
    --sizes 960x540,1920x1080 --skip numpy,onnx,torch --json "$out/field_render_baked.json"
# a bounded scene, where the occupancy grid makes the baked form sparse: lego (8 views at 200x200) trained for baking
# (configs/field-baked.json: docs/results/2026-11-28-baked-features.md), when the data is there (LEGO_DIR)
lego="${LEGO_DIR:-../shared/data/nerf_synthetic_lego}"
if [ -d "$lego" ]; then
    step field_lego_deferred 150 "$py" -m engine.cli train field --scene "$lego" --views 8 --downscale 4 --device cuda \
        --config configs/field-baked.json --out "$work/lego_deferred"
    step field_lego_export 120 "$py" -m engine.cli export field "$work/lego_deferred"
    step field_lego_baked 90 "$py" -m tools.bench_fields static "$work/lego_deferred/export" --run "$work/lego_deferred" \
        --sizes 960x540,1920x1080 --skip numpy,onnx,torch --json "$out/field_render_baked_lego.json"
fi
# a dynamic field trained for baking (D-NeRF lego at 200x200, 2000 steps on CUDA, configs/dynamic-baked.json:
# docs/results/2026-11-30-dynamic-baked-recipe.md), exported with its baked form (engine.fields.glbaked
# GlBakedDynamicRenderer) and both GL renderers timed at 960x540 and 1920x1080, the unbaked one also with its
# motion-vector pass ("gl + motion vectors", the Newton inversion that mvec is fed), when the data is there (DNERF_DIR)
dnerf="${DNERF_DIR:-../shared/data/dnerf_lego}"
if [ -d "$dnerf" ]; then
    step dyn_lego_deferred 300 "$py" -m engine.cli train dynamic --scene "$dnerf" --downscale 4 --steps 2000 \
        --device cuda --no-flip --config configs/dynamic-baked.json --out "$work/dyn_deferred"
    cp "$work/dyn_deferred/scores.json" "$out/dyn_deferred_scores.json" 2>/dev/null
    step dyn_lego_export 240 "$py" -m engine.cli export dynamic "$work/dyn_deferred"
    step dyn_lego_baked 120 "$py" -m tools.bench_fields dynamic "$work/dyn_deferred/export" --run "$work/dyn_deferred" \
        --sizes 960x540,1920x1080 --skip numpy,onnx,torch --json "$out/dyn_render_baked_lego.json"
fi
# (issue 45) the dynamic default (DeRF with the sparse flow prior, its SIFT on this machine's CPU) against K-Planes,
# 2000 steps each on CUDA, on a generated 5-camera rig (seed 3, 160x90, held-out cam2): train seconds beside the
# step's wall time (priors and the held-out renders included) and held-out PSNR
step dyn_rig 40 "$py" -m engine.cli render-rig "$work/rig3" --seed 3 --width 160 --height 90 --num-frames 24 \
    --num-cameras 5 --test-cameras 1
for kind in derf kplanes; do
    INTERLEAVE_SIFT_CACHE="$work/sift" step "dyn_$kind" 150 "$py" -m engine.cli train dynamic --scene "$work/rig3" \
        --train-cameras cam0,cam1,cam3 --test-cameras cam2 --test-every 2 --steps 2000 --seed 0 --device cuda \
        --no-flip --renderer torch --field.kind "$kind" --out "$work/dyn_$kind"
    cp "$work/dyn_$kind/scores.json" "$out/dyn_${kind}_scores.json" 2>/dev/null
done
# the correlation flow network trained on the GPU (SET=corrflow, above; not part of the default run)
if [[ "${SET:-}" == corrflow || " ${ONLY:-} " == *" cf_"* ]]; then
    cf="$work/corrflow"
    cf_channels="${CF_CHANNELS:-16,32,64,64,32,48}"
    cf_init=()
    [ "$cf_channels" = 16,32,64,64,32,48 ] && cf_init=(--init-from models/weights/corrflow.pt --lr 1.5e-4)
    cf_args=(--data "$cf/data" --pairs "$cf/pairs" --out "$cf/run" --depth --net-width 384 --crop 216x320 --ks 1,2,3,4
             --scenes smooth:5100:16,fast:5000:16,extreme:5016:8,medium:5024:8,gentle:5032:8 --device "${CF_DEVICE:-cuda}")
    step cf_pairs 300 "$py" -m models.flow.corrflow_train "${cf_args[@]}" --pairs-only --workers "${CF_WORKERS:-14}"
    step cf_train 480 "$py" -m models.flow.corrflow_train "${cf_args[@]}" --steps "${CF_STEPS:-3000}" \
        --batch-size "${CF_BATCH:-16}" --iterations "${CF_ITERATIONS:-6}" --channels "$cf_channels" --threads 4 "${cf_init[@]}"
    cp "$cf/run/metrics.jsonl" "$out/corrflow_metrics.jsonl" 2>/dev/null
    cp "$cf/run/config.json" "$out/corrflow_config.json" 2>/dev/null
    for it in 2 4; do
        step cf_export 60 "$py" -m export.corrflow "$cf/run/checkpoint.pt" "$out/corrflow_it$it.onnx" --iterations $it
    done
    # the validation sequences of docs/results/2026-11-29-no-vector-estimation.md (never trained on or scored)
    step cf_val 240 bash -c "$py - '$work/val' <<'PY'
import sys
from tools.heldout import render_set
for name, preset, seed in [('seed1005', 'gentle', 1005), ('seed1006', 'gentle', 1006), ('valfast7204', 'fast', 7204),
                           ('valfast7205', 'fast', 7205), ('valsmooth7953', 'smooth', 7953), ('valsmooth7954', 'smooth', 7954)]:
    print(render_set(sys.argv[1], name, {'seed': seed}, 640, 360, 16, preset=preset))
PY
$py docs/results/2026-11-29-no-vector-estimation.py epe \$(ls -d $work/val/*_640x360x16 | paste -sd,) 2,4 \
    corr,corr=$out/corrflow_it2.onnx,corr=$out/corrflow_it4.onnx,dis $out/corrflow_val.json"
fi
