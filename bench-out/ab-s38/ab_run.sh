#!/bin/bash
# alternate old (3a3801f, session 38.s start) and new (the working tree) `palpate run paper --sim`; wall clock of the
# whole process, each into a fresh --out; the disk cache warmed by both first
PY=/root/.pyenv/versions/3.11.7/bin/python3
for i in $(seq 1 $1); do
  for v in old new; do
    if [ $v = old ]; then D=/tmp/ab-s38old; else D=/work/main; fi
    rm -rf /tmp/s38/run_${v}_$i
    s=$(date +%s.%N)
    (cd $D && PYTHONPATH=$D $PY -m app.cli run paper --sim --out /tmp/s38/run_${v}_$i > /tmp/s38/run_${v}_$i.txt 2>&1)
    rc=$?
    e=$(date +%s.%N)
    echo "$v $i rc=$rc $(echo "$e - $s" | bc)"
  done
done
