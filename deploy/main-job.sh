#!/usr/bin/env bash
# The README's main job on the embedded default: start the service (SQLite, local artifact root, local Ray),
# submit a LeCO job on the default synthetic city through the API, follow it to the end, stop the service.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
PORT=${LECO_PORT:-8765}
export LECO_DATA_DIR=${LECO_DATA_DIR:-leco-data}
mkdir -p "$LECO_DATA_DIR"

$BIN/leco serve --port "$PORT" >"$LECO_DATA_DIR/serve.log" 2>&1 &
SERVER=$!
trap 'kill $SERVER 2>/dev/null; wait $SERVER 2>/dev/null || true' EXIT
for _ in $(seq 120); do
  $BIN/python -c "import urllib.request as u; u.urlopen('http://127.0.0.1:$PORT/readyz', timeout=2)" 2>/dev/null && break
  kill -0 $SERVER 2>/dev/null || { cat "$LECO_DATA_DIR/serve.log"; exit 1; }
  sleep 1
done
echo "service ready at http://127.0.0.1:$PORT (log: $LECO_DATA_DIR/serve.log)"
$BIN/leco submit --url "http://127.0.0.1:$PORT" --synthetic city:0 --method leco --profile cpu --workers 2 "$@"
