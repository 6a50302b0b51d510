#!/bin/bash
# alternate old (42e34cd) and new (working tree) runs of one command; wall clock of the whole process
PY=/root/.pyenv/versions/3.11.7/bin/python3
for i in $(seq 1 $1); do
  for v in old new; do
    if [ $v = old ]; then D=/tmp/ab-old; else D=/work/main; fi
    s=$(date +%s.%N)
    (cd $D && PYTHONPATH=$D $PY -m app.cli simulate paper --load indent --x-m 0.035 --depth-m 0.003 --json /tmp/s36/ab_${v}_$i.json > /tmp/s36/ab_${v}_$i.txt 2>&1)
    rc=$?
    e=$(date +%s.%N)
    echo "$v $i rc=$rc $(echo "$e - $s" | bc)"
  done
done
