#!/usr/bin/env bash
# One-shot GPU check of nrc, offline: install, CUDA tests, benchmarks (scripts/device_check.py says what each
# step does). Uses the interpreter that holds the GPU machine's CUDA torch: $PYTHON, else python3.
#   scripts/device_check.sh OUTDIR [--wheelhouse DIR] [--vdb PATH] [--budget 540] [--only STEP,...] [--dry-run]
#   scripts/device_check.sh --make-wheelhouse DIR [--python-version 3.12]    # on a connected machine, beforehand
set -uo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
exec "${PYTHON:-python3}" "$here/device_check.py" "$@"
