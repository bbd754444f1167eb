#!/usr/bin/env bash
# One device call: paper_speed.py runs with hashgrid_triton.RUN_REDUCTION set per run, in the order given,
# so that one call holds both orders of an A/B (join the tables with benchmarks/speed_ab.py).
#   RR_RUNS="dense:a none:b dense:c" RR_ARGS="--batches 1 8" bash benchmarks/run_reduction_ab.sh
# Each entry is mode:label; tags h200_rr_<mode>_<label>; carry .whl and outputs/gpu_refs. Results -> $OUT/rr.tgz.
set -uo pipefail
out=${OUT:-/tmp/out}/rr.d
mkdir -p "$out" /tmp/site
trap 'tar czf "${OUT:-/tmp/out}/rr.tgz" -C "$out" . && rm -rf "$out"' EXIT
trap 'exit 143' TERM
pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
export PYTHONPATH=/tmp/site:. HF_HUB_OFFLINE=1
for run in ${RR_RUNS:?mode:label entries}; do
  mode=${run%%:*}; label=${run#*:}
  timeout "${RR_TIMEOUT:-170}" python - "$mode" --device cuda --mode after --tag "h200_rr_${mode}_$label" \
    --store outputs/gpu_refs --out "$out" ${RR_ARGS:-} > "$out/rr_${mode}_$label.log" 2>&1 <<'PY'
import runpy
import sys

from morpheus_core.geometry import hashgrid_triton

hashgrid_triton.RUN_REDUCTION = sys.argv.pop(1)
sys.argv[0] = "benchmarks/paper_speed.py"
runpy.run_path("benchmarks/paper_speed.py", run_name="__main__")
PY
  echo "exit $?" >> "$out/rr_${mode}_$label.log"
done
