#!/usr/bin/env bash
# start: init and start a disposable PostgreSQL cluster on 127.0.0.1 and print its URL.
# stop: stop it and remove its files. Runs the server as the 'postgres' user when root.
set -euo pipefail
DIR=${HKTEX_PG_DIR:-/tmp/hktex-pg}
PORT=${HKTEX_PG_PORT:-55432}
BIN=$(dirname "$(ls /usr/lib/postgresql/*/bin/pg_ctl | sort -V | tail -n1)")
as_pg() { if [ "$(id -u)" = 0 ]; then su postgres -s /bin/bash -c "$*"; else bash -c "$*"; fi; }

case "${1:-start}" in
  start)
    as_pg "'$BIN/pg_ctl' -D '$DIR' stop -m immediate" >/dev/null 2>&1 || true
    rm -rf "$DIR"; mkdir -p "$DIR"
    [ "$(id -u)" = 0 ] && chown postgres "$DIR"
    as_pg "'$BIN/initdb' -D '$DIR' -A trust -U postgres" >/dev/null
    as_pg "'$BIN/pg_ctl' -D '$DIR' -w -l '$DIR/log' -o \"-h 127.0.0.1 -p $PORT -k '$DIR'\" start" >/dev/null
    as_pg "'$BIN/createdb' -h 127.0.0.1 -p $PORT -U postgres hktex_test"
    echo "postgresql+psycopg://postgres@127.0.0.1:$PORT/hktex_test"
    ;;
  stop)
    as_pg "'$BIN/pg_ctl' -D '$DIR' stop -m fast" >/dev/null 2>&1 || true
    rm -rf "$DIR"
    ;;
esac
