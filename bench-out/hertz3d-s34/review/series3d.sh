#!/bin/bash
# sequential 3D series; one computation at a time
export PALPATE_CACHE=0 PYTHONPATH=/work/main
PY=/root/.pyenv/versions/3.11.7/bin/python3
cd /work/main
O=/tmp/review34/out3d.jsonl; : > $O
for nu in 0.3 0.49; do
  for cfg in "0.1 0.35" "0.1 0.25" "0.07 0.35" "0.05 0.5"; do
    $PY /tmp/review34/run3d.py $nu $cfg 2.02 >> $O
  done
done
M=/tmp/review34/out3d_mirror.jsonl; : > $M
for nu in 0.3 0.49; do
  $PY /tmp/review34/run3d.py $nu 0.1 0.35 2.6 --mirror >> $M
  $PY /tmp/review34/run3d.py $nu 0.07 0.45 2.6 --mirror >> $M
done
# the claim's own bench, coarsest mesh only (W=20R, H=10R, nu=0.45, d/R=0.05, 56k DOFs)
$PY bench/hertz3d_stress.py --fine-r 0.1 > /tmp/review34/bench_claim_f0.1.jsonl
