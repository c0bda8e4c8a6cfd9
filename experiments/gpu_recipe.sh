#!/usr/bin/env bash
# Train one STN-Homography stage on a GPU machine with the Keras JAX backend (no TensorFlow needed),
# stage-1 pairs generated on the fly from a folder of images by worker processes.
#
#   experiments/gpu_recipe.sh IMAGE_DIR VAL_IMAGE_DIR MODEL_DIR [train_stage flags...]
#
# Defaults are the paper's schedule (91,000 steps: 1,000 warm-up + 90,000 cosine, batch 64,
# SGD 0.05 momentum 0.9), mixed bfloat16, SAMPLES_PER_IMAGE (default 3, the paper's) pairs per
# image generated once by the workers and trained from memory (--in_memory: 192 KB a pair;
# measured 79-83 steps/s on an H100), validation MACE on 300 fixed pairs of VAL_IMAGE_DIR (seed 1,
# three per image: the pairs `data_prep.make_dataset --split=test --seed=1` writes). Passing
# --noin_memory --fresh_pairs instead draws new pairs every data epoch in the workers (measured
# only 5.4-5.8 steps/s inside model.fit on the H100; see BENCHMARKS.md). Re-running the same
# command resumes from MODEL_DIR/checkpoint. The script then times batch-1 latency of 1/2/3 stages
# (JSON next to the model) and packs MODEL_DIR into MODEL_DIR.tar.gz to bring back.
# Needs: python3 with jax (CUDA), keras>=3, opencv-python-headless, numpy, absl-py, h5py.
# README "Training on a GPU with the JAX backend" gives the full procedure.
set -euo pipefail
if [ $# -lt 3 ]; then
  echo "usage: $0 IMAGE_DIR VAL_IMAGE_DIR MODEL_DIR [train_stage flags...]" >&2
  exit 2
fi
IMAGE_DIR=$1; VAL_DIR=$2; MODEL_DIR=$3; shift 3
export KERAS_BACKEND=${KERAS_BACKEND:-jax}
export PYTHONUNBUFFERED=1
PYTHON=${PYTHON:-python3}
WORKERS=${WORKERS:-$(( $(nproc) > 3 ? $(nproc) - 2 : 1 ))}
"$PYTHON" -m experiments.train_stage --image_dir="$IMAGE_DIR" --val_image_dir="$VAL_DIR" \
  --model_dir="$MODEL_DIR" --in_memory --samples_per_image="${SAMPLES_PER_IMAGE:-3}" \
  --workers="$WORKERS" --mixed_precision \
  --val_samples=300 --log_every=1000 --checkpoint_every=1000 "$@"
if [ -z "${SKIP_LATENCY:-}" ]; then
  "$PYTHON" -m experiments.benchmark_latency --policy=mixed_bfloat16 \
    --json_out="$MODEL_DIR/latency_mixed_bfloat16.json" > /dev/null
fi
tar -czf "$MODEL_DIR.tar.gz" -C "$(dirname "$MODEL_DIR")" "$(basename "$MODEL_DIR")"
echo "packed $MODEL_DIR.tar.gz"
