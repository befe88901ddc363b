#!/usr/bin/env bash
# A local PostgreSQL for the service's PostgreSQL tests, from Debian's packages.
#
# Idempotent and quick when already done: installs the server if missing, creates and starts
# the default cluster, and makes a role and a database for the tests. The role may create
# databases, so each test gets a scratch database of its own. The last line printed is the
# SQLAlchemy URL to export as REGTREE_TEST_POSTGRES_URL:
#
#   export REGTREE_TEST_POSTGRES_URL=$(bash .ci/postgres.sh | tail -n 1)
#
# Settings (environment): PG_ROLE (regtree), PG_PASSWORD (regtree), PG_DB (regtree),
# PG_PORT (the cluster's port, 5432 for a new cluster).
set -euo pipefail
ROLE=${PG_ROLE:-regtree}
PASSWORD=${PG_PASSWORD:-regtree}
DB=${PG_DB:-regtree}

log() { echo "postgres.sh: $*" >&2; }

if ! command -v pg_lsclusters >/dev/null || [ -z "$(ls /usr/lib/postgresql 2>/dev/null)" ]; then
  log "installing postgresql"
  export DEBIAN_FRONTEND=noninteractive
  apt-get install -y -qq postgresql >/dev/null 2>&1 \
    || { apt-get update -qq && apt-get install -y -qq postgresql >/dev/null; }
fi

VERSION=$(ls /usr/lib/postgresql | sort -V | tail -n 1)
if ! pg_lsclusters -h | awk '{print $1, $2}' | grep -qx "$VERSION main"; then
  log "creating cluster $VERSION/main"
  pg_createcluster "$VERSION" main >/dev/null
fi
PORT=$(pg_lsclusters -h | awk -v v="$VERSION" '$1 == v && $2 == "main" {print $3}')
PORT=${PG_PORT:-$PORT}
if ! pg_lsclusters -h | awk -v v="$VERSION" '$1 == v && $2 == "main" {print $4}' | grep -q online
then
  log "starting cluster $VERSION/main on port $PORT"
  pg_ctlcluster "$VERSION" main start
fi

psql_admin() { su postgres -c "psql -p $PORT -v ON_ERROR_STOP=1 -qAtX $*"; }
for _ in $(seq 1 50); do
  psql_admin "-c 'select 1'" >/dev/null 2>&1 && break
  sleep 0.2
done

if [ "$(psql_admin "-c \"select 1 from pg_roles where rolname = '$ROLE'\"")" != 1 ]; then
  log "creating role $ROLE"
  psql_admin "-c \"create role $ROLE login createdb password '$PASSWORD'\""
fi
if [ "$(psql_admin "-c \"select 1 from pg_database where datname = '$DB'\"")" != 1 ]; then
  log "creating database $DB"
  psql_admin "-c \"create database $DB owner $ROLE\""
fi

echo "postgresql+psycopg://$ROLE:$PASSWORD@127.0.0.1:$PORT/$DB"
