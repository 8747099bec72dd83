#!/usr/bin/env bash
# Rebuilds sitl/assets/replay/three.min.js: the parts of three.js that the race replay uses
# (three-entry.js), from the versions pinned in package-lock.json, minified into one
# classic script that defines the global THREE. The output is committed, so building
# sitl needs neither Node.js nor the network; this script is only for a version bump.
#   tools/replay/build-three.sh        (needs node and npm, from the npm registry)
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
out="$here/../../sitl/assets/replay/three.min.js"
cd "$here"
npm ci --no-audit --no-fund --silent
version="$(node -p "JSON.parse(require('fs').readFileSync('node_modules/three/package.json')).version")"
{
  printf '/* three.js %s (https://threejs.org): the exports of tools/replay/three-entry.js,\n' "$version"
  printf '   bundled by tools/replay/build-three.sh. Its licence, as the package ships it:\n\n'
  sed 's/^/   /' node_modules/three/LICENSE
  printf '*/\n'
  npx esbuild three-entry.js --bundle --minify --format=iife --global-name=THREE \
    --target=es2020 --legal-comments=none --log-level=warning
} > "$out.tmp"
mv "$out.tmp" "$out"
wc -c "$out"
