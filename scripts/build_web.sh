#!/usr/bin/env bash
# Builds the web page's script for `rllock serve`: three.js and esbuild from the npm registry (versions
# pinned in package-lock.json), src/main.js bundled and minified into orchestration/service/web/app.js,
# which is committed and ships in the package, so that neither users nor the tests need npm.
set -euo pipefail
cd "$(dirname "$0")/../orchestration/service/web"
npm ci --no-audit --no-fund
./node_modules/.bin/esbuild src/main.js --bundle --minify --format=esm --target=es2020 \
  --legal-comments=eof --outfile=app.js
echo "built $(pwd)/app.js ($(wc -c < app.js) bytes) with three $(node -p 'require("./node_modules/three/package.json").version')"
