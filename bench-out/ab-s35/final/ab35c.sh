#!/bin/bash
# A/B (final): 34d4237 against the working tree, one sitting, alternating; a warm-up simulate for the new code's key first
PY=/root/.pyenv/versions/3.11.7/bin/python3
OUT=/work/main/bench-out/ab-s35/final
mkdir -p $OUT
cd /work/main && PYTHONPATH=/work/main $PY -m app.cli simulate block3d --load indent --x-m 0.035 --y-m 0.035 --depth-m 0.003 --quiet --json $OUT/warmup.json > /dev/null 2>>$OUT/stderr.txt
run() {
  cmd=$1; v=$2; r=$3
  D=$([ $v = old ] && echo /tmp/ab-old || echo /work/main)
  cd $D
  if [ $cmd = predict ]; then args="predict block3d --grid 10x10 --depth-m 0.003"; else args="simulate block3d --load indent --x-m 0.035 --y-m 0.035 --depth-m 0.003"; fi
  s=$(date +%s.%N)
  PYTHONPATH=$D $PY -m app.cli $args --quiet --json $OUT/$cmd-$v-$r.json > /dev/null 2>>$OUT/stderr.txt
  rc=$?
  e=$(date +%s.%N)
  echo "$cmd $v $r rc=$rc $(echo "$e - $s" | bc) load=$(cut -d' ' -f1 /proc/loadavg)" | tee -a $OUT/ab.txt
}
for r in 1 2 3; do run predict old $r; run predict new $r; done
for r in 1 2; do run simulate old $r; run simulate new $r; done
