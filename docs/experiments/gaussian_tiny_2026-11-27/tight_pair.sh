#!/bin/bash
# two 10-minute synth tight Gaussian fits side by side (1 thread each): NAME1 "ARGS1" NAME2 "ARGS2"


for n in $1 $3; do rm -rf $n; mkdir -p $n; cp -r P_tight/ingest P_tight/project.json $n/; done
(bash tight_run.sh $1 $2 > $1.res 2>&1) &
(bash tight_run.sh $3 $4 > $3.res 2>&1) &
wait
