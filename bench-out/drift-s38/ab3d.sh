#!/bin/bash
export OPENBLAS_NUM_THREADS=1
P='import sys; sys.argv=["palpate"]+sys.argv[1:]; from app.entry import palpate; palpate()'
mkdir -p /tmp/ab3d
for s in 0 1 2 3 4 5; do
  for v in old new; do
    d=/tmp/ab-old; [ $v = new ] && d=/work/main
    extra=""; [ $s -ge 3 ] && extra="--truth-sensor-drift-n-per-s 5e-4"
    (cd $d && PYTHONPATH=$d python -c "$P" run block3d --sim --seed $s $extra --no-figure --out /tmp/ab3d/$v-$s) > /tmp/ab3d/$v-$s.log 2>&1
  done
done
echo done > /tmp/ab3d/DONE
