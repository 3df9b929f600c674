#!/usr/bin/env bash
# The first GPU run of the CUDA path: every check in one command, within 8 minutes on one
# H100/H200 (see scripts/validate_cuda.py for the steps). Writes OUT_DIR/summary.md (pass/fail
# per step, the device, the versions), OUT_DIR/summary.json, OUT_DIR/steps/*.log and
# OUT_DIR/benchmarks/cuda.{md,json} (copy those to docs/benchmarks/ to publish them).
#
#   scripts/validate_cuda.sh OUT_DIR              # on a machine with a GPU
#   scripts/validate_cuda.sh OUT_DIR --dry-run    # the same Python on the CPU at toy sizes
#
# Python: $PYTHON, else the repository's .venv, else python3. Exit status 0 when no step failed.
set -u
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(dirname "$here")"
if [ $# -lt 1 ] || [ "${1#-}" != "$1" ]; then
  echo "usage: $0 OUT_DIR [--dry-run] [--only STEP ...]" >&2
  exit 2
fi
out="$1"
shift
py="${PYTHON:-}"
if [ -z "$py" ]; then
  if [ -x "$root/.venv/bin/python" ]; then py="$root/.venv/bin/python"; else py="$(command -v python3)"; fi
fi
mkdir -p "$out"
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
# the whole run is bounded too (the steps' own limits add up to less)
limit=540
case " $* " in *" --dry-run "*) limit=900 ;; esac
timeout --kill-after=10 "$limit" "$py" "$here/validate_cuda.py" "$out" "$@" 2>&1 | tee "$out/validate.log"
status=${PIPESTATUS[0]}
if [ "$status" = 124 ] || [ "$status" = 137 ]; then
  echo "validate_cuda: stopped after ${limit} s; partial results in $out/summary.md" | tee -a "$out/validate.log"
fi
exit "$status"
