#!/bin/bash
# A/B: predict block3d (100 waypoints with stresses, stone scene + prior) and simulate block3d --load indent, cached
PY=/root/.pyenv/versions/3.11.7/bin/python3
OUT=/work/main/bench-out/ab-s35
for r in 1 2 3; do
  for v in old new; do
    D=$([ $v = old ] && echo /tmp/ab-old || echo /work/main)
    cd $D
    s=$(date +%s.%N)
    PYTHONPATH=$D $PY -m app.cli predict block3d --grid 10x10 --depth-m 0.003 --quiet --json $OUT/predict-$v-$r.json > /dev/null 2>>$OUT/stderr.txt
    rc=$?
    e=$(date +%s.%N)
    echo "predict $v $r rc=$rc $(echo "$e - $s" | bc) load=$(cut -d' ' -f1 /proc/loadavg)" | tee -a $OUT/ab.txt
  done
done
for r in 1 2; do
  for v in old new; do
    D=$([ $v = old ] && echo /tmp/ab-old || echo /work/main)
    cd $D
    s=$(date +%s.%N)
    PYTHONPATH=$D $PY -m app.cli simulate block3d --load indent --x-m 0.035 --y-m 0.035 --depth-m 0.003 --quiet --json $OUT/simulate-$v-$r.json > /dev/null 2>>$OUT/stderr.txt
    rc=$?
    e=$(date +%s.%N)
    echo "simulate $v $r rc=$rc $(echo "$e - $s" | bc) load=$(cut -d' ' -f1 /proc/loadavg)" | tee -a $OUT/ab.txt
  done
done
