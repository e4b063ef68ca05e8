#!/usr/bin/env bash
# Fault test of `flexsplat train`: after a first checkpoint, the run folder stops accepting writes. The rerun must fail
# with an error naming the file it could not write, and leave the previous state.safetensors loadable: a third run
# with writes allowed again resumes from it and ends byte-identical to an uninterrupted run.
#   tests/cli/write_fault.sh FLEXSPLAT CONFIG WORK_DIR full|readonly
# full: a full disk, as a file-size limit (ulimit -f, SIGXFSZ ignored, so write() fails with EFBIG) below the size of
#       state.safetensors; works for any user.
# readonly: chmod a-w on the run folder. Permissions do not bind root, so as root (the CI) the faulty run runs as
#       nobody (setpriv, else runuser); only if neither can switch users does the test exit 77 (ctest SKIP).
set -euo pipefail
[[ $# -eq 4 ]] || { echo "usage: $0 FLEXSPLAT CONFIG WORK_DIR full|readonly" >&2; exit 2; }
exe="$1" config="$2" work="$3" mode="$4"
as_user=()
if [[ "$mode" == readonly && $(id -u) -eq 0 ]]; then
  if setpriv --reuid=65534 --regid=65534 --clear-groups true 2>/dev/null; then
    as_user=(setpriv --reuid=65534 --regid=65534 --clear-groups)
  elif runuser -u nobody -- true 2>/dev/null; then
    as_user=(runuser -u nobody --)
  else
    echo "SKIP: running as root, where chmod a-w does not stop writes, and neither setpriv nor runuser can drop to nobody"
    exit 77
  fi
fi
rm -rf "$work"
mkdir -p "$work"
cmd=("$exe" train --quiet --config "$config" --data procedural)
"${cmd[@]}" --out "$work/ref" >"$work/ref.log" 2>&1 || { cat "$work/ref.log"; exit 1; }
"${cmd[@]}" --out "$work/run" --steps 2 >"$work/first.log" 2>&1 || { cat "$work/first.log"; exit 1; }
state="$work/run/state.safetensors"
before=$(cksum <"$state")

set +e
case "$mode" in
  full)
    blocks=$(( $(stat -c %s "$state") / 1024 / 2 ))
    # PMIx's shared-memory store would hit the limit inside MPI_Init (MPI builds); its hash store uses no files.
    ( trap '' XFSZ; ulimit -f "$blocks"; export PMIX_MCA_gds=hash; exec "${cmd[@]}" --out "$work/run" ) >"$work/fault.log" 2>&1
    status=$?
    expect="state\.safetensors"
    ;;
  readonly)
    chmod a-w "$work/run"
    if ((${#as_user[@]})); then
      # nobody must reach the program, its config and the run folder, and needs a TMPDIR of its own (Open MPI's
      # session directory; the CI's TMPDIR is private to root).
      mkdir -m 1777 "$work/tmp"
      for d in "$work/run" "$(dirname "$exe")" "$(dirname "$config")"; do
        "${as_user[@]}" test -r "$d" -a -x "$d" || { echo "SKIP: nobody cannot reach $d (a private parent folder)"; exit 77; }
      done
      ! "${as_user[@]}" test -w "$work/run" || { echo "FAIL: the run folder is writable for nobody" >&2; exit 1; }
      TMPDIR="$work/tmp" "${as_user[@]}" "${cmd[@]}" --out "$work/run" >"$work/fault.log" 2>&1
    else
      "${cmd[@]}" --out "$work/run" >"$work/fault.log" 2>&1
    fi
    status=$?
    chmod u+w "$work/run"
    expect="$work/run/"
    ;;
  *) echo "mode must be full or readonly" >&2; exit 2 ;;
esac
set -e
echo "faulty run: exit status $status: $(tr '\n' ' ' <"$work/fault.log")"
[[ $status -ne 0 ]] || { echo "FAIL: the run succeeded although its folder could not be written" >&2; exit 1; }
[[ $status -lt 128 ]] || { echo "FAIL: the run died from signal $((status - 128)) instead of reporting an error" >&2; exit 1; }
grep -q "$expect" "$work/fault.log" || { echo "FAIL: the error does not name the file under $work/run" >&2; exit 1; }
[[ "$(cksum <"$state")" == "$before" ]] || { echo "FAIL: $state changed" >&2; exit 1; }
"${cmd[@]}" --out "$work/run" >"$work/last.log" 2>&1 || { cat "$work/last.log"; echo "FAIL: resuming after the fault failed" >&2; exit 1; }
cmp "$work/ref/model.safetensors" "$work/run/model.safetensors" || { echo "FAIL: resumed model differs" >&2; exit 1; }
echo "PASS: clear error, previous checkpoint intact and resumable ($mode)"
