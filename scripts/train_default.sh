#!/usr/bin/env bash
# Reproduce the shipped default agent on CPU: synthetic dyadic sessions (+ the real BEAT2 clip) -> the three region
# codecs -> optional decoder fine-tuning (DECODER_REGIONS) -> LM tokens -> the gesture LM ->
# ecas/checkpoints/codecs/{upper,lower,face} and ecas/checkpoints/gesture_lm. The decoder stage freezes the encoders and
# quantizers, so it never changes the LM tokens.
#
#   bash scripts/train_default.sh                 # the shipped run (about 1.5 hours of wall time on 2 cores)
#   CODEC_REGIONS=lower CODECS_FROM=runs/default_v7 WORK=runs/default_v8 bash scripts/train_default.sh
#                                                 # only the lower codec anew (the other regions' data unchanged)
#   SESSIONS=2 CODEC_SESSIONS=2 MINUTES=0.5 CODEC_STEPS=20 DECODER_REGIONS=upper DECODER_STEPS=10 LM_EPOCHS=1 WORK=/tmp/tiny SHIP=/tmp/tiny/ship bash scripts/train_default.sh
#
# Every stage's wall time goes to $WORK/wall_times.tsv. Re-running reuses the synthetic data when it exists
# (SYNTHETIC=data/synthetic reuses the dataset of `ecas synthetic --out data/synthetic`).
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PY:-.venv/bin/python}
WORK=${WORK:-runs/default}
SHIP=${SHIP:-checkpoints}
SYNTHETIC=${SYNTHETIC:-$WORK/synthetic}  # its own copy: nothing else writes there while it trains
SESSIONS=${SESSIONS:-100}  # the LM trains on all of them
CODEC_SESSIONS=${CODEC_SESSIONS:-24}  # the codecs on the first ones
MINUTES=${MINUTES:-3}
SEED=${SEED:-0}
BEAT2_CLIP=${BEAT2_CLIP:-../shared/data/beat2/2_scott_0_1_1}
CODEC_CONFIG=${CODEC_CONFIG:-ecas/configs/codec/default_small.yaml}
LM_CONFIG=${LM_CONFIG:-ecas/configs/lm/default_small.yaml}
CODEC_STEPS=${CODEC_STEPS:-}  # every region, when set (tiny runs); otherwise each region's own below
UPPER_CODEC_STEPS=${UPPER_CODEC_STEPS:-${CODEC_STEPS:-12000}}  # held out (region alone) 16.0 mm at 8000 steps
LOWER_CODEC_STEPS=${LOWER_CODEC_STEPS:-${CODEC_STEPS:-5000}}  # held out 14.3 mm at 1500 steps, still falling
FACE_CODEC_STEPS=${FACE_CODEC_STEPS:-${CODEC_STEPS:-5000}}  # the face needs more steps to carry blinks as well as the jaw
CODEC_REGIONS=${CODEC_REGIONS:-upper lower face}  # the codecs trained here; the others are copied from ...
CODECS_FROM=${CODECS_FROM:-}  # ... this earlier run's $WORK (codecs/<region>, codec_<region>.json, its wall time)
DECODER_CONFIG=${DECODER_CONFIG:-ecas/configs/codec/default_small_finetune.yaml}
DECODER_REGIONS=${DECODER_REGIONS:-}  # none for the current ship (ecas/configs/codec/default_small_finetune.yaml says why)
DECODER_STEPS=${DECODER_STEPS:-}  # every region, when set (tiny runs); otherwise each region's own below
UPPER_DECODER_STEPS=${UPPER_DECODER_STEPS:-${DECODER_STEPS:-4000}}
LOWER_DECODER_STEPS=${LOWER_DECODER_STEPS:-${DECODER_STEPS:-3000}}
LM_EPOCHS=${LM_EPOCHS:-300}  # the shipped LM; trained on to the config's 450 (CE 3.05 -> 2.94) its elbows held still less
NICE=(nice -n "${NICE_LEVEL:-5}")
export OPENBLAS_NUM_THREADS=1

check_reuse() {  # before any stage: every region left out of CODEC_REGIONS can be copied as it shipped
  local region
  for region in upper lower face; do
    [[ " $CODEC_REGIONS " == *" $region "* ]] && continue
    if [ -z "$CODECS_FROM" ] || [ ! -f "$CODECS_FROM/codecs/$region/model.safetensors" ]; then
      echo "CODEC_REGIONS=\"$CODEC_REGIONS\" leaves out $region: set CODECS_FROM to an earlier run's WORK with" \
        "codecs/$region (CODECS_FROM=\"$CODECS_FROM\")" >&2
      return 1
    fi
    if [ -d "$CODECS_FROM/decoders/$region" ] && [[ " $DECODER_REGIONS " != *" $region "* ]]; then
      echo "$CODECS_FROM fine-tuned its $region decoder, which is not copied: add $region to DECODER_REGIONS" >&2
      return 1
    fi
  done
}

check_reuse
mkdir -p "$WORK"
TIMES="$WORK/wall_times.tsv"
: > "$TIMES"

timed() {  # timed NAME command...: run it and append "NAME<TAB>seconds" to $TIMES
  local name=$1 start=$SECONDS
  shift
  echo "== $name: $*" >&2
  "$@"
  printf '%s\t%d\n' "$name" $((SECONDS - start)) >> "$TIMES"
}

mix_data() {  # mix_data DIR N: a BEAT2-layout directory of the first N synthetic sessions plus the real clip
  local mix=$1 n=$2 id file
  rm -rf "$mix"
  mkdir -p "$mix"/{smplxflame_25,wave16k,whisper_transcription}
  head -n $((n + 1)) "$SYNTHETIC/train_test_split.csv" > "$mix/train_test_split.csv"
  for id in $(tail -n +2 "$mix/train_test_split.csv" | cut -d, -f1); do
    for file in "$SYNTHETIC"/*/"$id".*; do
      ln -s "$(realpath "$file")" "$mix/$(basename "$(dirname "$file")")/"
    done
  done
  if [ -f "$BEAT2_CLIP.npz" ]; then
    ln -s "$(realpath "$BEAT2_CLIP.npz")" "$mix/smplxflame_25/"
    ln -s "$(realpath "$BEAT2_CLIP.wav")" "$mix/wave16k/"
    printf '%s,train\n' "$(basename "$BEAT2_CLIP")" >> "$mix/train_test_split.csv"
  fi
}

reuse_codec() {  # reuse_codec REGION: an earlier run's codec, when its region's data did not change
  mkdir -p "$WORK/codecs"
  rm -rf "$WORK/codecs/$1"
  cp -r "$CODECS_FROM/codecs/$1" "$WORK/codecs/"
  cp "$CODECS_FROM/codec_$1.json" "$WORK/"
  grep "^codec_$1	" "$CODECS_FROM/wall_times.tsv" >> "$TIMES"
  # the run that trained it, for the model card: the earlier run's own record when it had copied it too
  if [ -f "$CODECS_FROM/codec_origin_$1" ]; then
    cp "$CODECS_FROM/codec_origin_$1" "$WORK/"
  else
    echo "$CODECS_FROM" > "$WORK/codec_origin_$1"
  fi
}

train_codecs() {  # the regions of $CODEC_REGIONS in parallel, each niced and single-threaded
  local region steps pids=()
  declare -A region_steps=([upper]=$UPPER_CODEC_STEPS [lower]=$LOWER_CODEC_STEPS [face]=$FACE_CODEC_STEPS)
  for region in upper lower face; do
    if [[ " $CODEC_REGIONS " != *" $region "* ]]; then
      reuse_codec "$region"
      continue
    fi
    steps=${region_steps[$region]}
    rm -f "$WORK/codec_origin_$region"  # trained here
    timed "codec_$region" "${NICE[@]}" "$PY" -m ecas.cli train-codec --config "$CODEC_CONFIG" --region "$region" \
      --data "$WORK/cache" --out "$WORK/codecs/$region" --steps "$steps" > "$WORK/codec_$region.json" \
      2> "$WORK/codec_$region.log" &
    pids+=($!)
  done
  for pid in "${pids[@]}"; do wait "$pid"; done
}

finetune_decoders() {  # each region of $DECODER_REGIONS in parallel -> $WORK/decoders/<region>
  local region pids=()
  local -A region_steps=([upper]=$UPPER_DECODER_STEPS [lower]=$LOWER_DECODER_STEPS)
  for region in $DECODER_REGIONS; do
    local steps=${region_steps[$region]:-$DECODER_STEPS}  # the face: DECODER_STEPS, else the config's
    "${NICE[@]}" "$PY" -m ecas.cli train-codec --config "$DECODER_CONFIG" --region "$region" --data "$WORK/cache" \
      --finetune-decoder "$WORK/codecs/$region" --out "$WORK/decoders/$region" \
      ${steps:+--steps "$steps"} > "$WORK/decoder_$region.json" 2> "$WORK/decoder_$region.log" &
    pids+=($!)
  done
  for pid in "${pids[@]}"; do wait "$pid"; done
}

shipped_codec() {  # the fine-tuned codec of a region when there is one
  if [ -f "$WORK/decoders/$1/model.safetensors" ]; then echo "$WORK/decoders/$1"; else echo "$WORK/codecs/$1"; fi
}

ship() {  # only what inference needs: codec weights + config, LM weights in bfloat16 + its metadata
  local region
  for region in upper lower face; do
    mkdir -p "$SHIP/codecs/$region"
    cp "$(shipped_codec "$region")"/{model.safetensors,config.yaml} "$WORK/codecs/$region/loss_curve.png" \
      "$SHIP/codecs/$region/"
    if [ -f "$WORK/decoders/$region/loss_curve.png" ]; then
      cp "$WORK/decoders/$region/loss_curve.png" "$SHIP/codecs/$region/decoder_loss_curve.png"
    fi
  done
  mkdir -p "$SHIP/gesture_lm"
  cp "$WORK/lm/lm.json" "$WORK/lm/losses.json" "$WORK/lm/loss_curve.png" "$WORK/lm_data/speakers.json" \
    "$SHIP/gesture_lm/"
  "$PY" - "$WORK/lm/lm.safetensors" "$SHIP/gesture_lm/lm.safetensors" <<'EOF'
import sys
import torch
from safetensors.torch import load_file, save_file
state = load_file(sys.argv[1])
save_file({k: (v.to(torch.bfloat16) if v.is_floating_point() else v).contiguous() for k, v in state.items()},
          sys.argv[2])
EOF
}

if [ ! -f "$SYNTHETIC/train_test_split.csv" ]; then
  timed synthetic "$PY" -m ecas.cli synthetic --out "$SYNTHETIC" --sessions "$SESSIONS" --minutes "$MINUTES" \
    --seed "$SEED" --jobs 2
fi
mix_data "$WORK/codec_data" "$CODEC_SESSIONS"
mix_data "$WORK/data" "$SESSIONS"
timed chunk_cache "$PY" -m gesture.data.build --root "$WORK/codec_data" --out "$WORK/cache"
timed codecs train_codecs
rm -rf "$WORK/decoders" "$WORK/lm_data" "$WORK/lm"
# The decoder fine-tuning keeps the encoders and quantizers, so the LM's tokens do not wait for it: both run at once.
timed decoders finetune_decoders &
decoders_pid=$!
timed tokenize "$PY" -m ecas.cli tokenize --root "$WORK/data" --codecs "$WORK/codecs" --out "$WORK/lm_data"
timed lm "${NICE[@]}" "$PY" -m ecas.cli train-lm --config "$LM_CONFIG" --data "$WORK/lm_data" \
  --codecs "$WORK/codecs" --out "$WORK/lm" --no-progress ${LM_EPOCHS:+--epochs "$LM_EPOCHS"}
wait "$decoders_pid"
timed ship ship
"$PY" scripts/model_cards.py "$WORK" "$SHIP"
du -sh "$SHIP"/* >&2
cat "$TIMES"
