#!/usr/bin/env bash
# Sets up .venv with energysim, its RL extra and its test tools; safe to run again (it skips what is done).
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
"${pip[@]}" -e ".[dev,rl]"

# The browser test (tests/test_viewer_browser.py) drives Debian's chromium through playwright, which is
# never allowed to download a browser of its own. Install chromium when it is missing and apt-get is
# usable (root); otherwise say so and let that test skip. ENERGYSIM_NO_BROWSER=1 skips this step.
if [ -z "${ENERGYSIM_NO_BROWSER:-}" ] && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup_env: installing Debian's chromium for the browser test (about a minute; log in .venv/apt-chromium.log)"
    if ! { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; } \
        >.venv/apt-chromium.log 2>&1 </dev/null; then
      echo "setup_env: installing chromium failed (see .venv/apt-chromium.log); the browser test will be skipped"
    fi
  else
    echo "setup_env: chromium is missing and apt-get needs root here; the browser test will be skipped"
  fi
fi
