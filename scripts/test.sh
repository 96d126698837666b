#!/usr/bin/env bash
# The test command: lint, then the default test suite (slow checks excluded; `-m slow` runs them).
# Starts a throw-away PostgreSQL on loopback for the queue tests when one is installed.
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate

# One compute thread per process: the suite runs worker processes and servers beside pytest,
# and oversubscribed OpenMP/BLAS/torch threads were measured 10-45x slower on 2 cores
# (docs/decisions.md). Override by exporting these before running.
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} OPENBLAS_NUM_THREADS=${OPENBLAS_NUM_THREADS:-1}
export MKL_NUM_THREADS=${MKL_NUM_THREADS:-1}

ruff check .
ruff format --check .

if [ -z "${HKTEX_TEST_PG_URL:-}" ]; then
  if url=$(bash scripts/pg-test-server.sh start 2>/tmp/hktex-pg.log); then
    export HKTEX_TEST_PG_URL="$url"
    trap 'bash scripts/pg-test-server.sh stop >/dev/null 2>&1 || true' EXIT
  else
    echo "note: no PostgreSQL started (see /tmp/hktex-pg.log); postgres tests will skip" >&2
  fi
fi

set +e
python -m pytest "$@"
rc=$?
set -e
exit $rc
