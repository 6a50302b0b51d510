#!/bin/bash
# usage: batch.sh LABEL PYTHONPATH
cd /tmp/side
export OPENBLAS_NUM_THREADS=1
for sc in x0.015 x0.018 x0.021 x0.025 edge50 corner50; do
 for seed in 0 1; do
  out=/tmp/side/b-$1-$sc-$seed
  [ -d $out ] && continue
  t0=$(date +%s.%N)
  PYTHONPATH=$2 python -c "import sys; from app.entry import palpate; sys.argv[0]=\"palpate\"; sys.exit(palpate())" run $sc.toml --sim --seed $seed --out $out > $out.log 2>&1 || true
  t1=$(date +%s.%N)
  echo "$sc $seed $(echo "$t1 - $t0" | bc)" >> /tmp/side/times-$1.txt
 done
done
