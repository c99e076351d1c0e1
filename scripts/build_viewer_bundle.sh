#!/usr/bin/env bash
# Rebuilds energysim/viewer/static/three.bundle.min.js: three.js and its OrbitControls as one minified
# ES module, so the viewer page needs no CDN, no import map and no network.
#
#     bash scripts/build_viewer_bundle.sh
#
# Needs node and npm (the npm registry); the versions are pinned so a rebuild gives the same file.
# three.js is MIT-licensed: its licence text is copied beside the bundle and esbuild keeps the
# @license comments at the end of the file.
set -euo pipefail
cd "$(dirname "$0")/.."
THREE_VERSION=0.187.0
ESBUILD_VERSION=0.28.2
static=energysim/viewer/static
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

(
  cd "$work"
  npm init -y >/dev/null
  npm install --silent --no-audit --no-fund "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION"
  cat > entry.js <<'JS'
export * from 'three';
export { OrbitControls } from 'three/addons/controls/OrbitControls.js';
JS
  npx --no-install esbuild entry.js --bundle --minify --format=esm --legal-comments=eof \
    --banner:js="/* three.js r${THREE_VERSION#0.} + OrbitControls, MIT licence (see THREE_LICENSE.txt). */" \
    --outfile=three.bundle.min.js
)
cp "$work/three.bundle.min.js" "$static/three.bundle.min.js"
cp "$work/node_modules/three/LICENSE" "$static/THREE_LICENSE.txt"
ls -l "$static/three.bundle.min.js" "$static/THREE_LICENSE.txt"
