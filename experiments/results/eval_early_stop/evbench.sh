#!/bin/bash
# Session 43: `aswarm eval` before (a scan to the clock, commit 7476c91) and after (the batch stops at its last
# episode's end, 1b5c91c), alternating, twice each, on the same machine. The old code is a worktree:
#   git worktree add /tmp/oldtree 7476c91
#   experiments/results/eval_early_stop/evbench.sh pretrained 500 race        > race_500.log
#   experiments/results/eval_early_stop/evbench.sh pretrained:lab 2000 lab    > lab_2000.log
# Each run is a fresh process (compile included; the second run of each finds JAX's persistent cache warm).
ROOT=$(git rev-parse --show-toplevel)
export PATH=$ROOT/.venv/bin:$PATH
unset PYTHONDONTWRITEBYTECODE
mkdir -p /tmp/logs
CK=$1; N=$2
for i in 1 2; do
  for v in old new; do
    if [ $v = old ]; then T=/tmp/oldtree; else T=$ROOT; fi
    s=$(date +%s.%N)
    (cd $T && PYTHONPATH=$T python -m aswarm.cli eval --checkpoint $CK --episodes $N --json --out /tmp/logs/evb_$v > /tmp/logs/evb_$v.json 2>/tmp/logs/evb_$v.err)
    e=$(date +%s.%N)
    echo "$CK $N $v run $i: $(echo "$e - $s" | bc) s; $(grep -o 'all ended by step [0-9]* of [0-9]*' /tmp/logs/evb_$v.err | tail -1)"
  done
done
python3 -c "
import json
a=json.load(open('/tmp/logs/evb_old/eval_'+'$3'+'.json')); b=json.load(open('/tmp/logs/evb_new/eval_'+'$3'+'.json'))
print('fields differing:', {k:(a[k],b.get(k)) for k in a if a[k]!=b.get(k)})"
