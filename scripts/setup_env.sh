#!/usr/bin/env bash
# Sets up .venv with energysim and its test tools; safe to run again (it skips what is done).
#
# On a machine without a CUDA GPU it installs the CPU build of torch: the "+cpu" version exists
# only as CPU wheels (a local wheel folder, or PyTorch's CPU index), so pip can never fall back
# to the multi-GB CUDA build. With a GPU present, the default (CUDA) build is what one wants.
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
pip=(.venv/bin/python -m pip install --quiet --disable-pip-version-check)
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    "${pip[@]}" "torch>=2.3"
  else
    # a local wheel folder (pip's find-links) first; PyTorch's CPU index only if that has none
    "${pip[@]}" "torch==2.13.0+cpu" 2>/dev/null \
      || "${pip[@]}" "torch==2.13.0+cpu" --extra-index-url https://download.pytorch.org/whl/cpu
  fi
fi
"${pip[@]}" -e ".[dev]"
