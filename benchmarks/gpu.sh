#!/usr/bin/env bash
# The GPU figures of docs/performance.md ("On a GPU", issue 48), in priority order within a time
# budget: forward and backward per scale (the paper's again without recompute), where a substep's
# time goes, a batch of 64 quick-start-size designs and where its substep goes, the paper-scale
# environments (the base of docs/studies.md's estimate of the paper's scale), one cell of Table 1
# at the paper's scale on a fraction of its budget (benchmarks/paper_cell.py), and last, if
# BASELINE names a checkout of an older commit, its forward rates on the same machine.
#
#   OUT=gpu-records BUDGET_S=540 bash benchmarks/gpu.sh          # from the repository root, on a CUDA machine
#
# Needs taichi (and numpy, scipy, pluggy, typer, rich; the Table 1 cell also torch, omegaconf,
# trimesh, stable-baselines3 and gymnasium, not wandb); the project need not be installed: its
# plugins are loaded by name. Each measurement appends JSON lines to $OUT as it ends, so a
# run cut short keeps what it finished.
set -u
OUT=${OUT:-gpu-records}
ARCH=${ARCH:-cuda}
BASELINE=${BASELINE:-}
SCALES=${SCALES:-tiny small paper large}      # of the forward and backward measurements
PROFILED=${PROFILED:-tiny paper}             # of the profile
ENV_SCALE=${ENV_SCALE:-paper}                # of the environments
CELL_SCALE=${CELL_SCALE:-paper}              # of the Table 1 cell
DEADLINE=$((SECONDS + ${BUDGET_S:-540}))
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 CODESIGN_DISABLE_PLUGIN_AUTOLOAD=1 CODESIGN_PLUGINS=codesign_mpm.plugin
export PYTHONPATH="$PWD:$PWD/plugins${PYTHONPATH:+:$PYTHONPATH}"

within_budget() {  # within_budget SECONDS COMMAND...: run it for at most SECONDS and what is left
    local cap=$1 left=$((DEADLINE - SECONDS)); shift
    if ((left < 20)); then echo "skipped (budget spent): $*" >&2; return; fi
    echo "$(date +%T) $*" >&2
    timeout $((cap < left ? cap : left)) "$@" || echo "ended with $?: $*" >&2
}

bench="python3 -m codesign bench"
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true; nproc; } > "$OUT/machine.txt"
scales() { for s in $1; do printf -- '--scale %s ' "$s"; done; }
within_budget 200 $bench engine --arch "$ARCH" $(scales "$SCALES") --measure forward --measure backward --frames 40 \
    --no-progress >> "$OUT/engine.jsonl"
# the paper's scale again with its whole episode in one segment (4.8 GB: memory a GPU has to spare)
within_budget 60 $bench engine --arch "$ARCH" --scale paper --measure backward --segment-memory 8192 \
    --frames 40 --no-progress >> "$OUT/engine.jsonl"
within_budget 100 $bench engine --arch "$ARCH" --profile $(scales "$PROFILED") --no-progress >> "$OUT/profile.jsonl"
within_budget 60 $bench engine --arch "$ARCH" --scale tiny --measure batch --members 64 --no-progress >> "$OUT/engine.jsonl"
# where the batch's substep goes: the 64 members' one launch against one member's
within_budget 60 $bench engine --arch "$ARCH" --profile --scale tiny --members 64 --no-progress >> "$OUT/profile.jsonl"
within_budget 120 $bench environments --arch "$ARCH" --scale "$ENV_SCALE" --env ground --env desert --env ocean \
    --no-progress >> "$OUT/environments.jsonl"
(export CODESIGN_PLUGINS=codesign_basics.plugin,codesign_mpm.plugin,codesign_designs.plugin,codesign_optimizers.plugin
 within_budget 300 python3 benchmarks/paper_cell.py --scale "$CELL_SCALE" >> "$OUT/paper_cell.jsonl")
if [[ -n "$BASELINE" ]]; then  # an older checkout's forward rates, for a before/after on this machine
    for scale in $SCALES; do
        [[ $scale == large ]] && continue  # not a scale of the older code
        (cd "$BASELINE" && export PYTHONPATH="$PWD:$PWD/plugins:$PYTHONPATH" && within_budget 40 python3 -c "
import json
try:
    from codesign_mpm.reports.bench import Case, measure_forward
except ImportError:  # a checkout from before codesign_mpm's rooms (2026-11-28)
    from codesign_mpm.bench import Case, measure_forward
print(json.dumps(dict(variant='baseline', scale='$scale',
                      **measure_forward(Case('$scale', 'float32', arch='$ARCH')))))") >> "$OUT/baseline.jsonl"
    done
fi
echo "$(date +%T) done" >&2
