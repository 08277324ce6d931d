#!/usr/bin/env bash
# One prepared device call (session 66): the real-time play check first, the static field (default command timed on
# CUDA; deferred -> baked GL renderer at 960x540 and 1920x1080), the dynamic default vs K-Planes on CUDA, the play
# check last. Results go to $RES (tarred to $OUT/res.tgz after every step). STEPS/SIZE env for a local dry run.
set -u
T0=$(date +%s)
BUDGET=${BUDGET:-560}               # seconds from the start after which no step starts
RES=${RES:-/tmp/res}; W=${WORK:-/tmp/work}; OUTD=${OUT:-/tmp/out}
mkdir -p "$RES" "$W" "$OUTD"
py=${PYTHON:-python3}
STEPS=${STEPS:-2000}; FSIZE=${FSIZE:-"--width 504 --height 378"}; DSIZE=${DSIZE:-"--width 160 --height 90"}
DEV=${DEV:-cuda}; HD=${HD:-960x540,1920x1080}; RT=${RT:-1920x1080}; RTF=${RTF:-120}
log="$RES/steps.log"
pack() { tar czf "$OUTD/res.tgz" -C "$RES" . 2>/dev/null; }
left() { echo $(( BUDGET - ($(date +%s) - T0) )); }
step() {  # step NAME LIMIT CMD...: skipped when the budget is spent; clamped to what is left
    local name=$1 limit=$2 l; shift 2
    l=$(left)
    if [ "$l" -lt 15 ]; then echo "== $name: SKIPPED (budget)" | tee -a "$log"; return; fi
    [ "$l" -lt "$limit" ] && limit=$l
    local s=$(date +%s.%N)
    echo "== $name (limit ${limit}s): $*" | tee -a "$log"
    timeout "$limit" "$@" >>"$RES/$name.out" 2>&1
    local rc=$?
    echo "== $name: exit $rc wall $(python3 -c "print(round($(date +%s.%N)-$s,2))") s (t=$(( $(date +%s) - T0 )))" \
        | tee -a "$log"
    tail -c 300 "$RES/$name.out" | tr '\r' '\n' | tail -n 3
    pack
}
{ nvidia-smi -L; $py --version; $py -c "import torch;print(torch.__version__, torch.cuda.is_available())"; } \
    >>"$log" 2>&1
nvidia-smi --query-gpu=timestamp,clocks.sm,clocks.mem,power.draw,utilization.gpu --format=csv -lms 200 \
    >"$RES/clocks.csv" 2>/dev/null &
clocks=$!
trap 'kill $clocks 2>/dev/null; pack' EXIT
play() {  # play TAG: the live loop headless on the gl path at k = 2 and 4 (scripts/bench_gpu.sh's play steps)
    for k in 2 4; do
        step "play_${1}_k$k" 60 $py -m engine.cli play --headless --backend gl --method mvec --renderer live \
            --width "${RT%x*}" --height "${RT#*x}" --k $k --frames "$RTF" --loop 240 --json "$RES/play_${1}_k$k.json"
    done
}
step gl_context 30 $py -c "from engine.geometry.backends import gl_renderer; print(gl_renderer())"
play first
step rt_warp 60 $py -m tools.bench_gl_warp --sizes "$RT" --repeats 20 --frames 4 --out "$W/scenes" \
    --json "$RES/rt_warp.json"
# issue 44: the 3-view forward-facing capture of scripts/bench_gpu.sh, default command on CUDA (timed), then deferred
step field_capture 40 $py -m engine.cli render-rig "$W/rig" --seed 7 $FSIZE --static --num-cameras 8 --test-cameras 2 \
    --baseline 0.25
step field_train 120 $py -m engine.cli train field --scene "$W/rig" --train-views cam1,cam3,cam6 --test-views cam2,cam5 \
    --device "$DEV" --steps "$STEPS" --out "$W/field"
cp "$W/field/scores.json" "$RES/field_scores.json" 2>/dev/null
step field_train_deferred 120 $py -m engine.cli train field --scene "$W/rig" --train-views cam1,cam3,cam6 \
    --test-views cam2,cam5 --device "$DEV" --steps "$STEPS" --field.shading deferred --out "$W/field_deferred"
cp "$W/field_deferred/scores.json" "$RES/field_deferred_scores.json" 2>/dev/null
step field_export_deferred 150 $py -m engine.cli export field "$W/field_deferred"
step field_render_baked 90 $py -m tools.bench_fields static "$W/field_deferred/export" --run "$W/field_deferred" \
    --sizes "$HD" --skip numpy,onnx,torch --json "$RES/field_render_baked.json"
# issue 45: the dynamic default (flow prior, SIFT on this CPU) against K-Planes on CUDA, rig seed 3
step dyn_rig 40 $py -m engine.cli render-rig "$W/rig3" --seed 3 $DSIZE --num-frames 24 --num-cameras 5 --test-cameras 1
export INTERLEAVE_SIFT_CACHE="$W/sift"
for kind in derf kplanes; do
    step "dyn_$kind" 150 $py -m engine.cli train dynamic --scene "$W/rig3" --train-cameras cam0,cam1,cam3 \
        --test-cameras cam2 --test-every 2 --steps "$STEPS" --seed 0 --device "$DEV" --no-flip --renderer torch \
        --field.kind $kind --out "$W/dyn_$kind"
    cp "$W/dyn_$kind/scores.json" "$RES/dyn_${kind}_scores.json" 2>/dev/null
done
BUDGET=$((BUDGET + 25)) play last
