#!/usr/bin/env bash
# The same commands on an accelerator (BENCHMARKS.md, "On a GPU"): the environment at growing world counts, the
# user's `aswarm train --scenario race` (the CPU defaults: 256 worlds, 4M env steps) and its policy on 1,000 unseen
# episodes, then the trainer's throughput at a batch sized for a GPU. Each step is capped in wall time so the whole
# check fits a short lease. Nothing here is GPU-specific: JAX picks the accelerator when one is installed.
#
#   bash experiments/gpu_check.sh OUT_DIR   # writes gpu.txt, bench.md, train_*.log, timing_*.json, eval_*.json
#   bash experiments/gpu_check.sh OUT_DIR NAME='TRAIN FLAGS' ...   # only these race runs, each evaluated
#   e.g. bash experiments/gpu_check.sh out gpu='--config configs/race_gpu.toml'
#
# Sizes (environment variables): WORLDS (bench), DEFAULT_STEPS (the default run; 0: the config's 4M), BIG_ENVS and
# BIG_STEPS (the GPU-sized run), CAP_BENCH / CAP_TRAIN / CAP_EVAL (seconds each step may run); ASWARM (the command,
# default `aswarm`) and PYTHON (default python3).
set -u
out=${1:?usage: gpu_check.sh OUT_DIR [NAME='TRAIN FLAGS' ...]}
shift
mkdir -p "$out"
aswarm=${ASWARM:-aswarm}
runs=$(mktemp -d)
export PYTHONUNBUFFERED=1

{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || echo "no nvidia-smi"
    ${PYTHON:-python3} -c "import jax, jaxlib; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, jax.devices())"
} > "$out/gpu.txt" 2>&1
cat "$out/gpu.txt"

train() {  # name, then aswarm train flags
    local name=$1; shift
    timeout "${CAP_TRAIN:-150}" $aswarm train --scenario race --out "$runs/$name" "$@" > "$out/train_$name.log" 2>&1
    echo "train $name: exit $?"
    cp "$runs/$name/timing.json" "$out/timing_$name.json" 2>/dev/null
    # Success by env step (appended to the log), kept even where the cap stopped the run before its timing was written.
    python3 - "$runs/$name/metrics.jsonl" >> "$out/train_$name.log" <<'PY'
import json, sys
try:
    rows = [json.loads(line) for line in open(sys.argv[1])]
except OSError:
    sys.exit("no metrics")
for r in rows[:: max(1, len(rows) // 12)] + rows[-1:]:
    print(r["env_steps"], round(r.get("episode/success", float("nan")), 3))
PY
    tr '\r' '\n' < "$out/train_$name.log" | tail -n 18
}
evaluate() {  # name: its policy on 1,000 unseen episodes (the seed `aswarm eval` reports by default)
    mkdir -p "$runs/eval_$1"
    timeout "${CAP_EVAL:-150}" $aswarm eval --checkpoint "$runs/$1" --episodes 1000 --seed 10000 \
        --out "$runs/eval_$1" 2>&1 | tail -n 18
    cp "$runs/eval_$1/eval_race.json" "$out/eval_$1.json" 2>/dev/null
}

if [ $# -gt 0 ]; then
    for spec in "$@"; do
        name=${spec%%=*}
        # shellcheck disable=SC2086  # the flags are meant to split
        train "$name" ${spec#*=}
        evaluate "$name"
    done
    rm -rf "$runs"
    exit 0
fi

timeout "${CAP_BENCH:-150}" $aswarm bench --scenario race --worlds "${WORLDS:-1024,16384}" --steps 100 --no-peer \
    --out "$out/bench.md" 2>&1
echo "bench: exit $?"
if [ "${DEFAULT_STEPS:-0}" = 0 ]; then train default; else train default --total-steps "$DEFAULT_STEPS"; fi
evaluate default
train big --num-envs "${BIG_ENVS:-4096}" --total-steps "${BIG_STEPS:-8000000}"
rm -rf "$runs"
