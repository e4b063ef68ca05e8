#!/usr/bin/env bash
# Fault test of `flexsplat train`: a run killed with SIGKILL at random moments, each time rerun with the same command,
# must end with a model.safetensors byte-identical to an uninterrupted run's.
#   tests/cli/kill_resume.sh FLEXSPLAT CONFIG WORK_DIR [KILLS (default 3)] [SEED (default 1)]
# Kill moments after each start, from the uninterrupted run's start-up time S and time per step D: uniform in (0, W)
# for every fourth kill, in (S, W) for the others, W = S + D x min(4, steps left), so kills land in start-up (MPI,
# config and log rewrites, checkpoint load), inside steps and inside checkpoint writes, and a long run takes many
# kills. A kill lands when the run dies of it (status 137); a run that ends first ("late") must have succeeded with
# the reference model, and the next attempt starts a fresh run. Attempts repeat until KILLS kills have landed, at most
# 4 x KILLS of them: fewer landed kills fail the test.
set -euo pipefail
[[ $# -ge 3 ]] || { echo "usage: $0 FLEXSPLAT CONFIG WORK_DIR [KILLS] [SEED]" >&2; exit 2; }
exe="$1" config="$2" work="$3" kills="${4:-3}" seed="${5:-1}"
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

landed=0 late=0 attempts=0
while ((landed < kills)); do
  attempts=$((attempts + 1))
  if ((attempts > 4 * kills)); then
    echo "FAIL: only $landed of $kills kills hit a running process in $((attempts - 1)) attempts (seed $seed)" >&2
    exit 1
  fi
  k=$((landed + 1))
  done_steps=$(last_step "$work/run/log.jsonl")
  left=$(( total - ${done_steps:-0} ))
  window=$(( startup_ms + step_ms * (left < 4 ? (left > 0 ? left : 1) : 4) ))
  from=$(( k % 4 == 1 ? 0 : startup_ms ))
  delay_ms=$(( from + (RANDOM * 32768 + RANDOM) % (window - from > 1 ? window - from : 1) ))
  "${cmd[@]}" --out "$work/run" >>"$work/run.log" 2>&1 &
  pid=$!
  sleep "$(printf '%d.%03d' $((delay_ms / 1000)) $((delay_ms % 1000)))"
  kill -KILL "$pid" 2>/dev/null || true
  rc=0
  wait "$pid" || rc=$?
  if ((rc == 137)); then
    landed=$((landed + 1))
    echo "kill $landed at ${delay_ms} ms (last logged step $(last_step "$work/run/log.jsonl"))"
  elif ((rc == 0)); then
    # The run ended before the signal: it resumed from the kills so far and must have finished the reference model.
    late=$((late + 1))
    cmp "$work/ref/model.safetensors" "$work/run/model.safetensors" ||
      { echo "FAIL: a run that finished after $landed kills differs from the uninterrupted run's (seed $seed)" >&2; exit 1; }
    echo "attempt $attempts at ${delay_ms} ms: late (the run had finished); a fresh run takes the next kills"
    rm -rf "$work/run"
  else
    tail -n 20 "$work/run.log"
    echo "FAIL: run of attempt $attempts exited with status $rc" >&2
    exit 1
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
echo "PASS: model.safetensors identical after $kills kills ($late late attempts), seed $seed"
