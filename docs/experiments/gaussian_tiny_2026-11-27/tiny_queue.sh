#!/bin/bash
# run lines of a queue file two at a time: each line "name iters args..."
q=$1
run_one() { bash tiny_run.sh "$@" > /dev/null 2>&1; }
while read -r a && read -r b; do
  run_one $a & run_one $b & wait
done < $q
