#!/usr/bin/env bash
# One device call: CUDA test pass of the device-aware tests, then the render and prior benchmarks.
# Run on the lent GPU machine from the repository root, carrying .whl (../shared/scripts/gpu-wheels.sh):
#   bash benchmarks/gpu_session.sh [quick|priors|stages|...]   results and logs -> $OUT/<mode>.tgz
# quick: every device-aware test on CUDA, render benchmarks, prior benchmark --quick (fits one 10-min call);
# priors: the CUDA prior tests and the full prior benchmark only.
# quality: benchmarks/quality.py on CUDA (QUALITY_ARGS picks size, parts, rows and scenes; default the gpu size),
#   results -> $OUT. The ablation records go on from benchmarks/results/quality_ablations_<tag>.records.jsonl
#   (QUALITY_RECORDS names it), so a call cut short by its time limit keeps what it finished.
# speed: the paper-schedule benchmark (benchmarks/paper_speed.py); SPEED_RUNS lists "mode:batches" runs,
#   e.g. "before:1 after:1,4"; carry outputs/gpu_refs (prepared on the CPU machine:
#   `python -c "from benchmarks.paper_speed import *; prepare_references(Path('outputs/gpu_refs'), preset('paper', ['device=cpu']))"`).
#   SPEED_TESTS=1 first runs the CUDA tests of the speed work. Results and profiles -> $OUT.
# early_stop: benchmarks/early_stop.py on CUDA (ES_SCHEDULES, ES_SCENES, ES_JOBS, ES_NAME, ES_ARGS), results -> $OUT.
# heads: the CUDA tests of the fused field heads, the NeRF render and the mesh renderer, then the NeRF stage of
#   paper_speed.py with MORPHEUS_FIELD_MLP=eager and auto (HEADS_BATCHES, default "1 4 8"); carry outputs/gpu_refs.
#   (The heads' launch-size sweep is its own command: python -m benchmarks.field_heads_kernel --tag h200.)
# ab: paper_speed.py (AB_ARGS) in this tree and in a reference tree made by reversing AB_PATCH (a diff of this
#   tree against the reference, e.g. `git diff HEAD -- morpheus_core > ab.patch`), reference first; tags
#   h200_${AB_NAME}_{ref,new}; carry outputs/gpu_refs. The two tables come from one call, so their ratio holds.
#   AB_ORDER (default "ref new") sets which runs first. Run both orders (two calls) and compare the pairs of
#   each call: in the VAE precision calls the second run read faster in 11 of 12 rows, whichever setting it ran
#   (benchmarks/results/vae_precision_h200.md).
# curve: fixed schedules under each oracle at once (ES_RUNS="stochastic:paper/40,paper/10:0,1:8 noise-free:paper/10:0:4",
#   ES_SCENES, ES_WORK), then the bake variants of benchmarks/bake_gap.py on the paper/10 stores (BAKE_TIMEOUT s, BAKE_NAME).
# fast: CUDA tests of the render phases, paper_speed.py of the paper and fast presets in both orders, then a
#   SIGKILL-and-resume check (FAST_ORDER, RESUME_SCENES; see the mode); carry outputs/gpu_refs.
# es_ab: benchmarks/early_stop.py (ES_* as in early_stop) in this tree and in a reference tree made by reversing
#   ES_PATCH, both at once, on the defaults (the fixed schedules: --variants fixed); records named
#   ${ES_NAME}_{ref,new}; summarise each with `python -m benchmarks.early_stop --from-records` and compare.
# variants: the CUDA prior tests, then paper_speed.py once per VARIANTS entry "name:key=value,key=value" (config
#   overrides, e.g. "vae32:priors.vae_dtype=float32 vaeauto:"), with V_ARGS; tags h200_<name>; carry outputs/gpu_refs.
#   All variants run in one call, so their ratios hold. V_TESTS=0 leaves the tests out.
# rr: paper_speed.py once per RR_RUNS entry "mode:label" with hashgrid_triton.RUN_REDUCTION set to mode (none, dense,
#   all), in the order given, with RR_ARGS; tags h200_rr_<mode>_<label>; carry outputs/gpu_refs. One call can hold
#   both orders of an A/B ("dense:a none:b dense:c"); compare each call's tables pair by pair.
# stages: the pipeline tests on CUDA and the stage step-time benchmark (paper and standard presets);
#   carry outputs/gpu_ref (a reference prepared on the CPU machine by `stage_speed.py --store outputs/gpu_ref`).
# Everything a mode writes under $OUT comes back as one $OUT/<mode>.tgz: the device tool returns only a
# few files per call, and a call that wrote more lost the rest. Unpack with `tar xzf <mode>.tgz`.
set -uo pipefail
mode=${1:-quick}
out=${OUT:-/tmp/out}/$mode.d
mkdir -p "$out" /tmp/site
trap 'tar czf "${OUT:-/tmp/out}/$mode.tgz" -C "$out" . && rm -rf "$out"' EXIT
trap 'exit 143' TERM  # a timeout's SIGTERM still packs what was written
pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
export PYTHONPATH=/tmp/site:. HF_HUB_OFFLINE=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$out/gpu.txt"
python -c "import torch, diffusers, transformers, peft; print(torch.__version__, diffusers.__version__, transformers.__version__, peft.__version__)" >> "$out/gpu.txt"
reference_tree() {  # $1: where; $2: a diff of this tree against the reference, reversed there
  rm -rf "$1" && cp -r . "$1" && patch -d "$1" -R -p1 -s < "$2"
}
early_stop_run() {  # $1: records name, $2: work folder, $3: log; ES_* pick the cells
  timeout "${ES_TIMEOUT:-540}" python -m benchmarks.early_stop --device cuda --jobs "${ES_JOBS:-8}" \
    --scenes "${ES_SCENES:-mug,bottle,box,vase,sneaker,lamp,chair,figure}" --seeds "${ES_SEEDS:-0,1,2}" \
    --work "$2" --results "$out" --name "$1" "${@:4}" > "$3" 2>&1
  echo "early_stop exit $?" >> "$3"
}
if [ "$mode" = early_stop ]; then
  # ES_SCHEDULES / ES_SCENES / ES_JOBS pick the cells; records are appended as they finish, so a
  # call cut short by its time limit still brings back what it finished (--from-records merges).
  name=${ES_NAME:-early_stop_h200}
  [ -f "benchmarks/results/$name.records.jsonl" ] && cp "benchmarks/results/$name.records.jsonl" "$out/"  # go on from it
  # shellcheck disable=SC2086  # ES_ARGS: more options, e.g. "--stop-rule reference --variants early"
  early_stop_run "$name" /tmp/es "$out/early_stop.log" --schedules "${ES_SCHEDULES:-draft}" ${ES_ARGS:-}
  exit 0
fi
if [ "$mode" = curve ]; then
  # The schedule curve: ES_RUNS entries "oracle:schedules:seeds:jobs" run at once (fixed schedules, ES_SCENES),
  # records ${ES_NAME}_<oracle> going on from benchmarks/results/ copies; GPU memory logged every 15 s; then,
  # while BAKE_TIMEOUT lasts, the bake variants of benchmarks/bake_gap.py on the stores of the BAKE_BASE (paper/10) runs.
  export PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True
  # ES_WORK inside the repository (an ignored path, e.g. outputs/es_curve) stays on a warm machine between calls:
  # a second call made at once goes on from the first call's stage checkpoints (runs longer than one call).
  work=${ES_WORK:-/tmp/es}
  (while true; do nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader >> "$out/gpu_mem.log"
     sleep 15; done) & monitor=$!
  pids=()
  # About 7.5 GiB per run at the paper/20 size: 12 runs at once ran out of an H100's 80 GB.
  fit=$(( $(nvidia-smi --query-gpu=memory.total --format=csv,noheader,nounits | head -1) / 8192 ))
  for entry in ${ES_RUNS:?oracle:schedules:seeds:jobs entries}; do
    IFS=: read -r oracle schedules seeds jobs <<< "$entry"
    [ "$jobs" -gt "$fit" ] && jobs=$fit
    name=${ES_NAME:-schedule_curve}_$oracle
    [ -f "benchmarks/results/$name.records.jsonl" ] && cp "benchmarks/results/$name.records.jsonl" "$out/"
    ES_SEEDS=$seeds ES_JOBS=$jobs early_stop_run "$name" "$work" "$out/early_stop_$oracle.log" \
      --schedules "$schedules" --variants fixed --oracle "$oracle" & pids+=($!)
  done
  wait "${pids[@]}"
  kill $monitor
  if [ "${BAKE_TIMEOUT:-0}" != 0 ]; then
    cat "$out"/*_stochastic.records.jsonl "$out"/*_noise-free.records.jsonl 2>/dev/null \
      | grep "\"base\": \"${BAKE_BASE:-paper/10}\"" > /tmp/bake_runs.jsonl
    timeout "$BAKE_TIMEOUT" python -m benchmarks.bake_gap --device cuda --work "$work" --jobs 8 \
      --records /tmp/bake_runs.jsonl --results "$out" --name "${BAKE_NAME:-bake_gap}" > "$out/bake_gap.log" 2>&1
    echo "bake_gap exit $?" >> "$out/bake_gap.log"
  fi
  exit 0
fi
if [ "$mode" = fast ]; then
  # The fast preset's call: the CUDA tests of the render phases and the hash grid; paper_speed.py at batch 1
  # for each preset of FAST_ORDER (default "paper fast fast paper": the A/B in both orders, one call);
  # then, with RESUME_SCENES, SIGKILL-and-resume runs of fast/20 against RESUME_RECORDS (benchmarks/gpu_resume.py).
  # Carry outputs/gpu_refs. Result names carry the GPU's own tag (h100, h200).
  tag=$(nvidia-smi --query-gpu=name --format=csv,noheader | grep -o 'H[0-9]*' | head -1 | tr 'H' 'h')
  if [ "${FAST_TESTS:-1}" = 1 ]; then
    MORPHEUS_TEST_DEVICE=cuda timeout "${FAST_TEST_TIMEOUT:-150}" python -m pytest -q -p no:cacheprovider \
      tests/test_cuda.py tests/test_hashgrid_triton.py tests/test_render_phases.py tests/test_cuda_volume.py \
      > "$out/pytest_cuda_fast.log" 2>&1
    echo "pytest exit $?" >> "$out/pytest_cuda_fast.log"
  fi
  i=0
  for p in ${FAST_ORDER-paper fast fast paper}; do  # FAST_ORDER="" times nothing
    i=$((i + 1))
    timeout "${SPEED_TIMEOUT:-150}" python benchmarks/paper_speed.py --device cuda --mode after --preset "$p" \
      --batches 1 --steps "${FAST_STEPS:-10}" --warmup 4 --tag "${tag}_${p}_$i" --store outputs/gpu_refs \
      --out "$out" > "$out/speed_${p}_$i.log" 2>&1
    echo "exit $?" >> "$out/speed_${p}_$i.log"
  done
  if [ -n "${RESUME_SCENES:-}" ]; then
    timeout "${RESUME_TIMEOUT:-240}" python -m benchmarks.gpu_resume --device cuda --schedule fast/20 \
      --records "benchmarks/results/${RESUME_RECORDS:-schedule_quality_h200_stochastic.records.jsonl}" \
      --scenes "$RESUME_SCENES" --seed 0 --stage "${RESUME_STAGE:-nerf}" --timeout 200 --work /tmp/gpu_resume \
      --results "$out" --name "gpu_resume_$tag" > "$out/gpu_resume.log" 2>&1
    echo "gpu_resume exit $?" >> "$out/gpu_resume.log"
  fi
  exit 0
fi
if [ "$mode" = es_ab ]; then
  reference_tree /tmp/es_ref "${ES_PATCH:?a diff of this tree against the reference}"
  export ES_JOBS=${ES_JOBS:-7}  # two processes of runs share the GPU
  for side in ref new; do
    dir=.; [ "$side" = ref ] && dir=/tmp/es_ref
    (cd "$dir" && early_stop_run "${ES_NAME:-es_ab}_$side" "/tmp/es_$side" "$out/early_stop_$side.log" \
      --schedules "${ES_SCHEDULES:-bench-cpu}" --variants fixed) &  # the defaults: the fixed schedule
  done
  wait
  exit 0
fi
if [ "$mode" = heads ]; then
  MORPHEUS_TEST_DEVICE=cuda timeout 150 python -m pytest -q -p no:cacheprovider tests/test_field_heads.py \
    tests/test_cuda_volume.py tests/test_raster.py tests/test_mesh_renderer.py tests/test_marching_tets.py \
    tests/test_dmtet.py > "$out/pytest_cuda_heads.log" 2>&1
  echo "pytest exit $?" >> "$out/pytest_cuda_heads.log"
  for heads in eager auto; do
    MORPHEUS_FIELD_MLP=$heads timeout 150 python benchmarks/paper_speed.py --device cuda --mode after --stages nerf \
      --batches ${HEADS_BATCHES:-1 4 8} --steps 10 --warmup 4 --tag "h200_heads_$heads" --store outputs/gpu_refs \
      --out "$out" ${SPEED_ARGS:-} > "$out/speed_heads_$heads.log" 2>&1
    echo "exit $?" >> "$out/speed_heads_$heads.log"
  done
  exit 0
fi
if [ "$mode" = ab ]; then
  reference_tree /tmp/ab_ref "${AB_PATCH:?a diff of this tree against the reference}"
  for side in ${AB_ORDER:-ref new}; do
    dir=.; [ "$side" = ref ] && dir=/tmp/ab_ref
    (cd "$dir" && timeout "${AB_TIMEOUT:-200}" python benchmarks/paper_speed.py --device cuda --mode after \
      --tag "h200_${AB_NAME:-ab}_$side" --store outputs/gpu_refs --out "$out" ${AB_ARGS:-}) > "$out/ab_$side.log" 2>&1
    echo "exit $?" >> "$out/ab_$side.log"
  done
  exit 0
fi
if [ "$mode" = rr ]; then
  for run in ${RR_RUNS:?mode:label entries}; do
    m=${run%%:*}; label=${run#*:}
    timeout "${RR_TIMEOUT:-170}" python - "$m" --device cuda --mode after --tag "h200_rr_${m}_$label" \
      --store outputs/gpu_refs --out "$out" ${RR_ARGS:-} > "$out/rr_${m}_$label.log" 2>&1 <<'PY'
import runpy
import sys

from morpheus_core.geometry import hashgrid_triton

hashgrid_triton.RUN_REDUCTION = sys.argv.pop(1)
sys.argv[0] = "benchmarks/paper_speed.py"
runpy.run_path("benchmarks/paper_speed.py", run_name="__main__")
PY
    echo "exit $?" >> "$out/rr_${m}_$label.log"
  done
  exit 0
fi
if [ "$mode" = variants ]; then
  if [ "${V_TESTS:-1}" = 1 ]; then
    MORPHEUS_TEST_DEVICE=cuda timeout "${V_TEST_TIMEOUT:-90}" python -m pytest -q -p no:cacheprovider \
      tests/test_cuda_priors.py tests/test_prior_runtime.py > "$out/pytest_cuda_variants.log" 2>&1
    echo "pytest exit $?" >> "$out/pytest_cuda_variants.log"
  fi
  for v in ${VARIANTS:?name:key=value,... entries}; do
    name=${v%%:*}; sets=()
    IFS=, read -ra kvs <<< "${v#*:}"
    for kv in "${kvs[@]}"; do [ -n "$kv" ] && sets+=(--set "$kv"); done
    timeout "${V_TIMEOUT:-200}" python benchmarks/paper_speed.py --device cuda --mode after --tag "h200_$name" \
      --store outputs/gpu_refs --out "$out" "${sets[@]}" ${V_ARGS:-} > "$out/variant_$name.log" 2>&1
    echo "exit $?" >> "$out/variant_$name.log"
  done
  exit 0
fi
if [ "$mode" = stages ]; then
  MORPHEUS_TEST_DEVICE=cuda timeout 300 python -m pytest -q -p no:cacheprovider tests/test_pipeline.py \
    tests/test_optimise.py -k "not unsafe_photo" > "$out/pytest_cuda_pipeline.log" 2>&1
  echo "pytest exit $?" >> "$out/pytest_cuda_pipeline.log"
  for p in paper standard; do
    timeout 150 python benchmarks/stage_speed.py --preset $p --device cuda --steps 30 --tag h200 \
      --store outputs/gpu_ref > "$out/stage_speed_$p.log" 2>&1
  done
  tar czf "$out/results_h200.tgz" benchmarks/results/stage_speed_*h200*
  exit 0
fi
if [ "$mode" = speed ]; then
  if [ "${SPEED_TESTS:-0}" = 1 ]; then
    MORPHEUS_TEST_DEVICE=cuda timeout 200 python -m pytest -q -p no:cacheprovider tests/test_cuda.py \
      tests/test_hashgrid.py tests/test_hashgrid_triton.py tests/test_cuda_volume.py \
      > "$out/pytest_cuda_speed.log" 2>&1
    echo "pytest exit $?" >> "$out/pytest_cuda_speed.log"
  fi
  for run in ${SPEED_RUNS:-after:1,4,8,16}; do
    m=${run%%:*}; b=${run#*:}
    timeout ${SPEED_TIMEOUT:-400} python benchmarks/paper_speed.py --device cuda --mode "$m" --batches ${b//,/ } \
      --profile --tag h200 --store outputs/gpu_refs --out "$out" ${SPEED_ARGS:-} > "$out/speed_$m.log" 2>&1
    echo "exit $?" >> "$out/speed_$m.log"
  done
  exit 0
fi
if [ "$mode" = quality ]; then  # QUALITY_ARGS, e.g. "--size cpu --scenes all --rows findings --jobs 12"
  [ -n "${QUALITY_RECORDS:-}" ] && [ -f "benchmarks/results/$QUALITY_RECORDS" ] && cp "benchmarks/results/$QUALITY_RECORDS" "$out/"
  [ -f benchmarks/results/findings.json ] && cp benchmarks/results/findings.json "$out/"
  timeout ${QUALITY_TIMEOUT:-560} python -m benchmarks.quality --device cuda --results "$out" \
    ${QUALITY_ARGS:---size gpu} > "$out/quality.log" 2>&1
  echo "quality exit $?" >> "$out/quality.log"
  exit 0
fi
if [ "$mode" = priors ]; then
  timeout 100 python -m pytest -q -p no:cacheprovider tests/test_cuda_priors.py > "$out/pytest_cuda_priors.log" 2>&1
  echo "pytest exit $?" >> "$out/pytest_cuda_priors.log"
  timeout 420 python benchmarks/prior_speed.py --tag h200 > "$out/prior_speed.log" 2>&1
  tar czf "$out/results_h200.tgz" benchmarks/results/prior_speed_h200.*
  exit 0
fi
MORPHEUS_TEST_DEVICE=cuda timeout 170 python -m pytest -q -p no:cacheprovider \
  tests/test_cameras.py tests/test_hashgrid.py tests/test_nerf.py tests/test_volume.py tests/test_raster.py \
  tests/test_mesh_renderer.py tests/test_texture.py tests/test_tets.py tests/test_dmtet.py tests/test_marching_tets.py \
  tests/test_mesh_regularisers.py tests/test_cuda.py tests/test_cuda_priors.py > "$out/pytest_cuda.log" 2>&1
echo "pytest exit $?" >> "$out/pytest_cuda.log"
timeout 90 python benchmarks/field_speed.py --device cuda --tag h200 > "$out/field_speed.log" 2>&1
timeout 90 python benchmarks/raster_speed.py --device cuda --tag h200 > "$out/raster_speed.log" 2>&1
timeout 210 python benchmarks/prior_speed.py --quick --tag h200 > "$out/prior_speed.log" 2>&1
tar czf "$out/results_h200.tgz" benchmarks/results/*h200*
