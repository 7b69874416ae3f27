#!/usr/bin/env bash
# Kept for old callers: the check is scripts/gpu_check.py (python3 scripts/gpu_check.py --help).
exec "${PYTHON:-python3}" "$(dirname "${BASH_SOURCE[0]}")/gpu_check.py" "$@"
