#!/usr/bin/env bash
# One command on the lent GPU machine for the paper's schedule (docs/gpu.md, "The paper's schedule
# in chunks"), run from the repository root with the JAX backend and no TensorFlow:
#
#   experiments/paper_schedule_gpu.sh stage            # keep the photographs carried this call
#   experiments/paper_schedule_gpu.sh probe            # + steps/s at several steps_per_execution
#   experiments/paper_schedule_gpu.sh chunk SECONDS    # + resume stage $STAGE, stop before SECONDS
#   PART=sequence2 experiments/paper_schedule_gpu.sh chunk SECONDS  # + another run (--part)
#   experiments/paper_schedule_gpu.sh semi SECONDS     # + issue 63's rows, stop at SECONDS
#
# Every mode first copies the parts this call carried under .devdata/part-K/ (made here by
# `python -m experiments.device_photographs`) into /tmp/stnh-data, which stays on the machine
# between calls: the photographs travel over several calls (each call carries at most 64 MiB, the
# working tree included, and a call removes what an earlier one carried). It also installs .whl/
# (keras, namex, optree wheels for the machine's Python: docs/gpu.md) once. `probe` leaves its
# JSON in /tmp/probe.json; a later `chunk` on the same machine trains with the fastest
# steps_per_execution it measured with the training callbacks (50 without a probe). What comes
# back is written to $OUT: probe.json, chunk.log, paper_schedule.tgz (the ledger and the stages
# and parts this call finished, with their records) and resume_NAME.tgz (an unfinished stage's or part's committed
# checkpoint, NAME stageK or the part). A chunk
# that finishes its stage goes on with the next one, up to stage 3, in the time left. `semi`
# trains and evaluates the semi-supervised experiment's rows (experiments.semi_supervised
# --in_memory at the CPU budget; SEMI_BUDGET=tiny for a try) from the coco_mini photographs,
# resuming from semi_supervised/in_memory/, and sends back semi.log and semi_supervised.tgz (that
# folder without model files: configurations, evaluations, an unfinished model's checkpoint,
# the table).
set -u -o pipefail
mode=${1:?stage, probe, chunk or semi}
out=${OUT:-/tmp/paper_schedule_out}
data=/tmp/stnh-data
mkdir -p "$out" "$data"
for part in .devdata/part-*/; do  # each holds its files under their paths in the whole set
  [ -d "$part" ] && cp -r "$part". "$data/"
done
train=$(find "$data/coco_mini/train" "$data/photos_extra" -type f -name '*.jpg' 2>/dev/null | wc -l)
test=$(find "$data/coco_mini/test" -type f -name '*.jpg' 2>/dev/null | wc -l)
echo "photographs on this machine: $train for training (1848 needed), $test for validation (100)"
if [ ! -d /tmp/site/keras ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || { echo "no .whl/ carried yet"; [ "$mode" = stage ] || exit 2; }
fi
export PYTHONPATH=/tmp/site:$PWD KERAS_BACKEND=jax PYTHONUNBUFFERED=1
workers=$(( $(nproc) - 2 ))
[ "$mode" = stage ] && exit 0
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader

if [ "$mode" = probe ]; then
  # coco_mini/train: in the first part carried (photos_extra comes later)
  timeout 240 python3 -m experiments.benchmark_stream --image_dir="$data/coco_mini/train" \
    --workers="$workers" --samples_per_image=2 --alone_batches=20 --modes=array \
    --steps_per_epoch=100 --epochs=3 --steps_per_execution=1,10,50 --callbacks=none,training \
    --json_out="$out/probe.json" 2>&1 | grep -v -e "^WARNING" -e "^I0000" | tail -20
  cp "$out/probe.json" /tmp/probe.json || { echo "the probe wrote no probe.json"; exit 4; }
  exit 0
fi

if [ "$mode" = semi ]; then
  seconds=${2:?semi needs its time limit in seconds}
  budget=${SEMI_BUDGET:-cpu}
  coco=$(find "$data/coco_mini/train" -type f -name '*.jpg' 2>/dev/null | wc -l)
  if [ "$budget" = cpu ] && { [ "$coco" != 219 ] || [ "$test" != 100 ]; }; then
    echo "expected the 219 + 100 coco_mini photographs in $data: carry them first"
    exit 3
  fi
  semi=(python3 -m experiments.semi_supervised --budget="$budget" --in_memory
        --image_dir="$data/coco_mini/train" --test_image_dir="$data/coco_mini/test"
        --output_dir=/tmp/stnh-runs/semi --repo_dir=semi_supervised/in_memory)
  spe=50; [ "$budget" = cpu ] || spe=1  # 50 divides the CPU budget's intervals (500, 100)
  echo "semi-supervised rows, budget $budget, time limit $seconds s, $workers workers"
  timeout "$seconds" "${semi[@]}" --workers="$workers" --steps_per_execution="$spe" 2>&1 \
    | grep -v -e "^WARNING" -e "^I0000" | tee "$out/semi.log"
  status=$?
  "${semi[@]}" --save_only 2>&1 | tail -1 | tee -a "$out/semi.log"  # after a stop at the limit
  cp /tmp/stnh-runs/semi/semi_supervised.md /tmp/stnh-runs/semi/semi_supervised.json \
    semi_supervised/in_memory/ 2>/dev/null
  tar czf "$out/semi_supervised.tgz" --exclude='*.keras' semi_supervised/in_memory
  exit $status
fi

seconds=${2:?chunk needs its time limit in seconds}
stage=${STAGE:-1}
part=${PART:-hierarchy}
if [ "$part" = hierarchy ]; then what=(--stage="$stage" --last_stage=3); else what=(--part="$part"); fi
if [ "$train" != 1848 ] || [ "$test" != 100 ]; then
  echo "expected 1848 training and 100 validation photographs in $data: carry the rest first"
  exit 3
fi
spe=$(python3 - <<'EOF'
import json, os
best = (0.0, 50)
if os.path.exists("/tmp/probe.json"):
    for key, r in json.load(open("/tmp/probe.json"))["fit"].items():
        if key.endswith("+callbacks"):
            k = int(key.split("/spe")[1].split("+")[0])
            best = max(best, (r["steps_per_s"], k))
print(best[1])
EOF
)
echo "${what[*]}, steps_per_execution $spe, time limit $seconds s, $workers workers"
touch /tmp/stnh-call-start  # the models this call writes are newer: only they go back
timeout $((seconds + 60)) python3 -m experiments.paper_schedule "${what[@]}" \
  --time_limit_s="$seconds" --workers="$workers" --steps_per_execution="$spe" \
  --image_dir="$data/coco_mini/train,$data/photos_extra" \
  --val_image_dir="$data/coco_mini/test" --runs_dir=/tmp/stnh-runs/paper_schedule \
  --device="$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1)" 2>&1 \
  | grep -v -e "^WARNING" -e "^I0000" | tee "$out/chunk.log"
status=$?
# What the chunks write, not the whole folder, in archives of at most 16 MiB each (what comes
# back): the ledger and the finished stages in paper_schedule.tgz, each unfinished stage's
# committed checkpoint with its saved estimates (12 MiB) in resume_NAME.tgz.
back="paper_schedule/ledger.json"  # (merged here: python -m experiments.paper_schedule --merge_back)
[ -e paper_schedule/ledger.pending.json ] && back="$back paper_schedule/ledger.pending.json"
for f in paper_schedule/*.keras; do  # each stage or part this call finished, with its record
  # (those sent from here come back unchanged: all of them would pass the 16 MiB an archive may
  # have once the 10:1 row is finished)
  [ "$f" -nt /tmp/stnh-call-start ] && back="$back $f" && [ -e "${f%.keras}.json" ] \
    && back="$back ${f%.keras}.json"
done
for d in paper_schedule/resume/*/; do
  [ -d "$d" ] && name=$(basename "$d") && tar czf "$out/resume_$name.tgz" "paper_schedule/resume/$name"
done
tar czf "$out/paper_schedule.tgz" $back
exit $status
