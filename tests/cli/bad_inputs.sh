#!/usr/bin/env bash
# The issue's bad inputs end with exit code 1 and a message naming the problem, never a crash: no images, a missing
# file, a file that is not a picture, a one-pixel photo, a model file holding NaN, a model file lacking a tensor, a
# folder without cameras.json. Photos of mixed channel counts (gray, gray + alpha, RGB, RGBA; each read as RGBA) are
# not an error: they give a .glb with their 4 cameras.
#   bad_inputs.sh FLEXSPLAT MODEL OBJECT_DIR DATA_DIR WORK_DIR
set -uo pipefail
flexsplat=$1 model=$2 object=$3 data=$4 work=$5
rm -rf "$work" && mkdir -p "$work" || exit 1
failures=0
expect_error() {  # pattern, then the program's arguments
  local pattern=$1 err code
  shift
  err=$("$flexsplat" "$@" 2>&1 >/dev/null)
  code=$?
  if [ "$code" -ne 1 ] || ! grep -q -- "$pattern" <<<"$err"; then
    echo "FAIL: flexsplat $*: exit code $code, expected 1 and a message with '$pattern':"
    echo "$err"
    failures=$((failures + 1))
  else
    echo "refused as expected: $(grep -- "$pattern" <<<"$err" | head -1)"
  fi
}
spot=$object/images/008.png
out=(-o "$work/out.glb")

expect_error "needs at least one IMAGE" reconstruct --model "$model" "${out[@]}"
expect_error "cannot open" reconstruct "$work/absent.png" --model "$model" "${out[@]}"
printf 'not a picture' >"$work/text.png"
expect_error "cannot decode" reconstruct "$spot" "$work/text.png" --model "$model" "${out[@]}"
expect_error "smaller than one 7 x 7 patch" reconstruct "$spot" "$data/one_pixel.png" --model "$model" "${out[@]}"
expect_error "must be full, local or local:WINDOW" eval "$object" --model "$model" --self-attention windowed
expect_error "camera source 'bogus' is not one of: model, orbit" eval "$object" --model "$model" --cameras bogus
expect_error "camera source 'orbit' needs the object probability of a match head" reconstruct "$spot" "$spot" \
  --model "$model" --cameras orbit "${out[@]}"
expect_error "5000 Gaussians requested; the decoder has 4096 queries" eval "$object" --model "$model" --gaussians 5000
# Numeric options: the whole value must parse (no "1e3" read as 1), and the message names the option.
expect_error "\-\-gaussians '1e3': expected an integer" reconstruct "$spot" --model "$model" --gaussians 1e3 "${out[@]}"
expect_error "\-\-refine 'nan' must be a positive number" reconstruct "$spot" --model "$model" --refine nan "${out[@]}"
expect_error "\-\-seed '-1': expected an integer in \[0, 2^64)" eval "$object" --model "$model" --seed -1
mkdir -p "$work/no_cameras/images" && cp "$spot" "$work/no_cameras/images/000.png"
expect_error "cameras.json': missing" eval "$work/no_cameras" --model "$model"

# Model files: the shipped one with a NaN in the decoder's first tensor, and with that tensor renamed (missing).
header_len=$(od -An -t u8 -N8 "$model" | tr -d ' ')
name=appearance.decoder.init_head.bias
entry=$(head -c $((8 + header_len)) "$model" | grep -ao "\"$name\":{[^}]*}")
begin=$(sed 's/.*"data_offsets":\[\([0-9]*\),.*/\1/' <<<"$entry")
cp "$model" "$work/nan.safetensors"
printf '\x00\x00\xc0\x7f' | dd of="$work/nan.safetensors" bs=1 seek=$((8 + header_len + begin)) conv=notrunc status=none
expect_error "non-finite" reconstruct "$spot" --model "$work/nan.safetensors" "${out[@]}"
at=$(head -c $((8 + header_len)) "$model" | grep -abo "\"$name\"" | cut -d: -f1)
cp "$model" "$work/missing.safetensors"
printf 'X' | dd of="$work/missing.safetensors" bs=1 seek=$((at + ${#name})) conv=notrunc status=none
expect_error "lacks 1 of the" reconstruct "$spot" --model "$work/missing.safetensors" "${out[@]}"

# The run-time flags those refusals guard: local self-attention with its window, a smaller Gaussian budget.
if "$flexsplat" eval "$object" --model "$model" --quiet --max-targets 2 --self-attention local:256 --gaussians 600 \
     --json "$work/local.json" >/dev/null 2>"$work/local.err" && grep -q '"self_attention": "local:256"' "$work/local.json"; then
  echo "eval --self-attention local:256 --gaussians 600: recorded in $work/local.json"
else
  echo "FAIL: eval --self-attention local:256 --gaussians 600:"
  cat "$work/local.err"
  failures=$((failures + 1))
fi
if "$flexsplat" reconstruct "$data/gray_40x30.png" "$data/gray_alpha_30x40.png" "$data/rgb_64x48.png" "$spot" \
     --model "$model" -o "$work/mixed.glb" 2>"$work/mixed.err" | grep -q "4 camera(s)"; then
  echo "mixed channel counts: $work/mixed.glb with 4 cameras"
else
  echo "FAIL: reconstruct of gray, gray + alpha, RGB and RGBA photos:"
  cat "$work/mixed.err"
  failures=$((failures + 1))
fi
expect_error "\-\-index '7x': expected an integer in \[0, 3\]" render "$work/mixed.glb" --index 7x -o "$work/r.png"
exit $((failures > 0))
