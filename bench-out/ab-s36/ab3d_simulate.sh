#!/bin/bash
PY=/root/.pyenv/versions/3.11.7/bin/python3
for i in $(seq 1 $1); do
  for v in old new; do
    if [ $v = old ]; then D=/tmp/ab-old; else D=/work/main; fi
    s=$(date +%s.%N)
    (cd $D && PYTHONPATH=$D $PY -m app.cli simulate block3d --load indent --x-m 0.035 --y-m 0.035 --depth-m 0.003 --quiet --json /tmp/s36/ab3d_${v}_$i.json > /dev/null 2>&1)
    rc=$?
    e=$(date +%s.%N)
    echo "$v $i rc=$rc $(echo "$e - $s" | bc)"
  done
done
