#!/usr/bin/env bash
# Runs every test of the workspace. PostgreSQL-backed tests need a server on 127.0.0.1:5432
# (trust auth); this script starts the local cluster when it is not answering.
set -euo pipefail
cd "$(dirname "$0")/.."

pg_up() { pg_isready -h 127.0.0.1 -p 5432 -q 2>/dev/null; }
if command -v pg_isready >/dev/null 2>&1 && ! pg_up; then
  echo "PostgreSQL is not answering on 127.0.0.1:5432: starting it" >&2
  if command -v pg_ctlcluster >/dev/null 2>&1 && [ -d /etc/postgresql ]; then
    pg_ctlcluster --skip-systemctl-redirect "$(ls /etc/postgresql | head -n1)" main start || true
  fi
  for _ in $(seq 1 30); do pg_up && break; sleep 1; done
fi
if command -v pg_isready >/dev/null 2>&1 && ! pg_up; then
  echo "error: PostgreSQL is required by the farm tests and could not be started" >&2
  exit 1
fi
export CVFARM_TEST_PG="${CVFARM_TEST_PG:-postgres://postgres@127.0.0.1:5432/postgres}"

exec cargo nextest run --workspace --locked "$@"
