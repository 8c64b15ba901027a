#!/bin/bash
# two 10-minute synth small Gaussian fits side by side (1 thread each): NAME1 "ARGS1" NAME2 "ARGS2"


for n in $1 $3; do rm -rf $n; mkdir -p $n; cp -r P_small/ingest P_small/project.json $n/; done
(bash small10_run.sh $1 $2 > $1.res 2>&1) &
(bash small10_run.sh $3 $4 > $3.res 2>&1) &
wait
