#!/usr/bin/env bash
# Train the STN-Homography hierarchy on a GPU machine with the Keras JAX backend (no TensorFlow
# needed), pairs generated from a folder of images by worker processes and held in memory.
#
#   experiments/gpu_recipe.sh IMAGE_DIR VAL_IMAGE_DIR OUT_DIR [train_stage flags...]
#
# Trains OUT_DIR/stage1 .. OUT_DIR/stage$STAGES (STAGES default 1) one after another, as the
# paper's hierarchy: stage k's pairs are made in memory from the predictions of stages 1..k-1
# (--prev_stages; the paper's offline re-generation, without TFRecords). Defaults are the paper's
# schedule per stage (91,000 steps: 1,000 warm-up + 90,000 cosine, batch 64, SGD 0.05 momentum
# 0.9), mixed bfloat16, SAMPLES_PER_IMAGE pairs per image (default 3, the paper's; with a small
# folder such as coco_mini's 219 photographs use more, e.g. 1000: 219,000 pairs, 48 KB each in
# memory) generated once by the workers (--in_memory; measured 79-83 steps/s on an H100 at the
# CPU budget), validation MACE on 300 fixed pairs of VAL_IMAGE_DIR (seed 1, three per image: the
# pairs `data_prep.make_dataset --split=test --seed=1` writes, carried through the earlier stages
# for stage k). Extra flags go to every stage (e.g. --train_steps=30000 --checkpoint_every=1000);
# with STAGES=1, `--noin_memory --fresh_pairs` draws new pairs every data epoch in the workers
# instead (later stages need the fixed in-memory set).
# Re-running the same command resumes each unfinished stage from its checkpoint and skips the
# finished ones, so a run can be split across calls of limited length. The script then times
# batch-1 latency of 1/2/3 stages (OUT_DIR/latency_mixed_bfloat16.json) and packs each stage into
# OUT_DIR/stageK.tar.gz (model, config, result, logs; no checkpoint) to bring back; evaluate them
# with `python -m experiments.evaluate --model_dir=OUT/stage1,OUT/stage2 --data_dir=...`.
# Needs: python3 with jax (CUDA), keras>=3, opencv-python-headless, numpy, absl-py, h5py.
# docs/gpu.md ("Training on a GPU machine with the JAX backend") gives the full procedure.
set -euo pipefail
if [ $# -lt 3 ]; then
  echo "usage: $0 IMAGE_DIR VAL_IMAGE_DIR OUT_DIR [train_stage flags...]" >&2
  exit 2
fi
IMAGE_DIR=$1; VAL_DIR=$2; OUT_DIR=$3; shift 3
export KERAS_BACKEND=${KERAS_BACKEND:-jax}
export PYTHONUNBUFFERED=1
PYTHON=${PYTHON:-python3}
STAGES=${STAGES:-1}
# each worker holds every decoded photograph (about 8.5 GiB for COCO's 118,000: docs/scale.md):
# at most 6 by default, so that COCO's pairs and the workers fit 128 GiB
WORKERS=${WORKERS:-$(( $(nproc) > 8 ? 6 : ($(nproc) > 3 ? $(nproc) - 2 : 1) ))}
mkdir -p "$OUT_DIR"
prev=""
for k in $(seq 1 "$STAGES"); do
  dir="$OUT_DIR/stage$k"
  if [ ! -f "$dir/model.keras" ]; then
    "$PYTHON" -m experiments.train_stage --stage="$k" ${prev:+--prev_stages="$prev"} \
      --image_dir="$IMAGE_DIR" --val_image_dir="$VAL_DIR" --model_dir="$dir" --in_memory \
      --samples_per_image="${SAMPLES_PER_IMAGE:-3}" --workers="$WORKERS" --mixed_precision \
      --val_samples=300 --log_every=1000 --checkpoint_every=1000 "$@"
  fi
  prev="${prev:+$prev,}$dir"
done
if [ -z "${SKIP_LATENCY:-}" ]; then
  "$PYTHON" -m experiments.benchmark_latency --policy=mixed_bfloat16 \
    --json_out="$OUT_DIR/latency_mixed_bfloat16.json" > /dev/null
fi
for k in $(seq 1 "$STAGES"); do
  tar -czf "$OUT_DIR/stage$k.tar.gz" --exclude=checkpoint -C "$OUT_DIR" "stage$k"
  echo "packed $OUT_DIR/stage$k.tar.gz"
done
