#!/bin/bash
# The ablation table's command (benchmarks/vision_table.py) on one GPU, a scene per call, as it ran on an
# H200 for benchmarks/results/vision_table_gpu.md (docs/ablation.md, "The table's command on one H200").
#
#   SCENE=acrobot MODELS="KeyCLD KeyCLD-NC NODE2 FC" OUT=/tmp/out LIMIT=480 JOBS=8 \
#       bash benchmarks/vision_table_gpu.sh
#
# Render the scene's frames first where dm_control is installed (`keyvision render --scene keycld/<scene>
# --out runs/gpu-table/<scene>/data`, as the table's command does) and bring them along: a machine
# without MuJoCo trains and evaluates from them. Starts CUDA MPS, samples nvidia-smi every 15 s, stops
# the table after LIMIT seconds (its trainings checkpointed, every model it trained evaluated) and then
# writes the table of what finished; copies the table, its figures, the evaluations and the models'
# files (without checkpoints) to OUT. Each call adds its scene to the table under NAME (same recipe,
# same device), so the scenes of several calls make one table.
set -u
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
OUT=${OUT:-/tmp/out}; LIMIT=${LIMIT:-480}; TOUT=${TOUT:-runs/gpu-table}
SCENE=${SCENE:-pendulum}; MODELS=${MODELS:-KeyCLD KeyCLD-NC NODE2 FC}; NAME=${NAME:-vision_table_gpu}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,memory.total --format=csv > "$OUT/gpu.txt" 2>&1
(nvidia-cuda-mps-control -d && echo "MPS on") || echo "no MPS"
(while true; do
    nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader >> "$OUT/gpu.txt" 2>/dev/null
    sleep 15
done) &
sampler=$!
table=(python3 benchmarks/vision_table.py --scenes "$SCENE" --models $MODELS --seeds 3 --ablation-seeds 3
       --out "$TOUT" --results "$NAME" "$@")
start=$(date +%s)
timeout -s INT "$LIMIT" "${table[@]}" --jobs "${JOBS:-8}" > "$OUT/table.log" 2>&1
rc=$?
echo "table rc $rc after $(( $(date +%s) - start )) s" | tee -a "$OUT/table.log"
if [ $rc -ne 0 ]; then  # stopped at LIMIT: the table of the models that finished
    "${table[@]}" --report >> "$OUT/table.log" 2>&1
fi
kill $sampler
cp benchmarks/results/"$NAME".json benchmarks/results/"$NAME".md benchmarks/results/"${NAME}"_*"$SCENE".png "$OUT"/
tar czf "$OUT/evaluations.tgz" --exclude=data --exclude='*.png' --exclude='*.gif' --exclude='*.eqx' \
    --exclude='*.npz' -C "$TOUT" "$SCENE"
tar czf "$OUT/models.tgz" --exclude=data --exclude='*-evaluate' --exclude='checkpoint*' --exclude='model-*.eqx' \
    --exclude='*.npz' -C "$TOUT" "$SCENE"
ls -la "$OUT"
