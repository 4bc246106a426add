#!/usr/bin/env bash
# Builds the web page's script for `rllock serve`: three.js and esbuild from the npm registry (versions
# pinned in package-lock.json), src/main.js bundled and minified into orchestration/service/web/app.js,
# which is committed and ships in the package, so that neither users nor the tests need npm.
#
# The bundle's first line names the SHA-256 of its sources: every file under src/ (sorted by path) and
# package-lock.json, each hashed as its path, a NUL, its length in bytes, a NUL, then its bytes.
# tests/test_web_bundle.py computes the same and fails when they differ, that is, when src/ or the
# lock changed without a rebuild. The same sources give the same bundle, byte for byte.
set -euo pipefail
cd "$(dirname "$0")/../orchestration/service/web"

sources_sha256() {
  local path
  {
    find src -type f -print0 | LC_ALL=C sort -z | while IFS= read -r -d '' path; do
      printf '%s\0%s\0' "$path" "$(wc -c < "$path" | tr -d ' ')"
      cat "$path"
    done
    printf '%s\0%s\0' package-lock.json "$(wc -c < package-lock.json | tr -d ' ')"
    cat package-lock.json
  } | sha256sum | cut -d' ' -f1
}

digest="$(sources_sha256)"
npm ci --no-audit --no-fund
./node_modules/.bin/esbuild src/main.js --bundle --minify --format=esm --target=es2020 \
  --legal-comments=eof --outfile=app.js \
  "--banner:js=/*! rllock web page: built by scripts/build_web.sh from src/ and package-lock.json, sources sha256:$digest; edit src/, then rebuild */"
echo "built $(pwd)/app.js ($(wc -c < app.js) bytes) with three $(node -p 'require("./node_modules/three/package.json").version'), sources sha256:$digest"
