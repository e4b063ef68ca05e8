#!/usr/bin/env bash
# Fault test of `flexsplat train`: a run killed with SIGKILL at random moments, each time rerun with the same command,
# must end with a model.safetensors byte-identical to an uninterrupted run's.
#   tests/cli/kill_resume.sh FLEXSPLAT CONFIG WORK_DIR [KILLS (default 3)] [SEED (default: random)]
# Kill moments after each start, from the uninterrupted run's start-up time S and time per step D: uniform in (0, W)
# for every fourth kill, in (S, W) for the others, W = S + D x min(4, steps left), so kills land in start-up (MPI,
# config and log rewrites, checkpoint load), inside steps and inside checkpoint writes, and a long run takes many
# kills; a kill after the run already finished is counted as "late".
set -euo pipefail
[[ $# -ge 3 ]] || { echo "usage: $0 FLEXSPLAT CONFIG WORK_DIR [KILLS] [SEED]" >&2; exit 2; }
exe="$1" config="$2" work="$3" kills="${4:-3}" seed="${5:-$(( $(date +%s%N) % 1000000 ))}"
RANDOM=$seed
rm -rf "$work"
mkdir -p "$work"
cmd=("$exe" train --quiet --config "$config" --data procedural)

start=$(date +%s%N)
"${cmd[@]}" --out "$work/ref" >"$work/ref.log" 2>&1 || { cat "$work/ref.log"; echo "FAIL: uninterrupted run failed" >&2; exit 1; }
ref_ms=$(( ($(date +%s%N) - start) / 1000000 ))
train_ms=$(grep -o '"seconds":[0-9.]*' "$work/ref/log.jsonl" | tail -n 1 | cut -d: -f2 | awk '{printf "%d", $1 * 1000}')
startup_ms=$(( ref_ms > train_ms ? ref_ms - train_ms : 0 ))
last_step() { grep -o '"step":[0-9]*' "$1" 2>/dev/null | tail -n 1 | cut -d: -f2 || true; }
total=$(last_step "$work/ref/log.jsonl")
step_ms=$(( train_ms / (total > 0 ? total : 1) + 1 ))
echo "uninterrupted run: ${ref_ms} ms (start-up ${startup_ms} ms); $kills kills, seed $seed"

late=0
for ((k = 1; k <= kills; ++k)); do
  done_steps=$(last_step "$work/run/log.jsonl")
  left=$(( total - ${done_steps:-0} ))
  window=$(( startup_ms + step_ms * (left < 4 ? (left > 0 ? left : 1) : 4) ))
  from=$(( k % 4 == 1 ? 0 : startup_ms ))
  delay_ms=$(( from + (RANDOM * 32768 + RANDOM) % (window - from > 1 ? window - from : 1) ))
  "${cmd[@]}" --out "$work/run" >>"$work/run.log" 2>&1 &
  pid=$!
  sleep "$(printf '%d.%03d' $((delay_ms / 1000)) $((delay_ms % 1000)))"
  if kill -KILL "$pid" 2>/dev/null; then
    wait "$pid" 2>/dev/null || true
    step=$(last_step "$work/run/log.jsonl")
    echo "kill $k at ${delay_ms} ms (last logged step ${step:-none})"
  else
    # The run ended before the signal: it must have succeeded.
    wait "$pid" || { tail -n 20 "$work/run.log"; echo "FAIL: run $k failed on its own" >&2; exit 1; }
    late=$((late + 1))
    echo "kill $k at ${delay_ms} ms: late (the run had finished)"
  fi
done
# A temp file of a writer killed mid-write, planted so that its removal is checked whatever the kills hit.
true & dead=$!
wait "$dead"
mkdir -p "$work/run"
echo partial >"$work/run/state.safetensors.tmp${dead}_0"
"${cmd[@]}" --out "$work/run" >>"$work/run.log" 2>&1 || { tail -n 20 "$work/run.log"; echo "FAIL: the final resume failed" >&2; exit 1; }
if ! cmp "$work/ref/model.safetensors" "$work/run/model.safetensors"; then
  echo "FAIL: $work/run/model.safetensors differs from the uninterrupted run's (seed $seed)" >&2
  exit 1
fi
leftover=$(find "$work/run" -name '*.safetensors.tmp*' | wc -l)
[[ $leftover -eq 0 ]] || { ls -la "$work/run"; echo "FAIL: $leftover temp files of killed checkpoint writes remain" >&2; exit 1; }
echo "PASS: model.safetensors identical after $kills kills ($late late), seed $seed"
