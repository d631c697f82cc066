#!/bin/bash
# extra student arm on a table1 run's teacher+encoder: arm.sh NAME TASK SEED ARM "distill flags"
set -e
N=$1; T=$2; S=$3; ARM=$4; FLAGS=$5
base=$N-$T-s$S
export MUJOCO_GL=egl
python recipes/distill.py --name $base-$ARM --seed $S --threads 1 --no-progress --teacher runs/online_dt/$base-teacher \
  --encoder runs/train_encoder/$base-encoder --eval-episodes 0 --parallel $FLAGS
python recipes/evaluate.py --name $base-eval-$ARM --seed $S --threads 1 --no-progress --policy runs/distill/$base-$ARM \
  --trials 100 --videos 0 --parallel
