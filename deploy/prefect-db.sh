#!/usr/bin/env bash
# A PostgreSQL database for the Prefect server: Debian's postgresql package, one cluster in a
# folder of its own, listening on 127.0.0.1 only, with a generated password.
#
#   eval "$(bash deploy/prefect-db.sh start [DIR] [PORT])"   # exports PREFECT_API_DATABASE_CONNECTION_URL
#   bash deploy/prefect-db.sh url [DIR]                      # the export line again
#   bash deploy/prefect-db.sh stop [DIR]
#
# DIR defaults to runs/prefect-db, PORT to 5433 (a system PostgreSQL keeps 5432). `start` is
# idempotent: an existing cluster is started, not re-created. As root the server runs as the
# `postgres` user (PostgreSQL refuses root), so DIR's parent folders must be readable by it.
# Messages go to stderr; stdout carries only the export line.
set -euo pipefail

cmd=${1:-}
dir=${2:-runs/prefect-db}
port=${3:-5433}
say() { echo "prefect-db: $*" >&2; }
die() { say "$*"; exit 1; }

case "$cmd" in start|stop|url) ;; *) die "usage: bash deploy/prefect-db.sh start|stop|url [DIR] [PORT]";; esac

bin=""
if command -v initdb >/dev/null 2>&1; then
  bin=$(dirname "$(readlink -f "$(command -v initdb)")")
else
  bin=$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1 || true)
fi
[ -n "$bin" ] && [ -x "$bin/pg_ctl" ] \
  || die "PostgreSQL's server is not installed: \`apt-get install postgresql\` (Debian), then run this again"

mkdir -p "$dir"
dir=$(cd "$dir" && pwd)
as=()
if [ "$(id -u)" -eq 0 ]; then
  as=(runuser -u postgres --)
  chown postgres: "$dir"
  "${as[@]}" test -w "$dir" \
    || die "the postgres user cannot write $dir (a parent folder is closed to it): open the parents to it (chmod o+x) or choose a DIR under /var/lib or /srv"
fi
pg() { "${as[@]}" "$bin/$1" "${@:2}"; }
url() {
  echo "export PREFECT_API_DATABASE_CONNECTION_URL=postgresql+asyncpg://prefect:$(cat "$dir/password")@127.0.0.1:$(cat "$dir/port")/prefect"
}

case "$cmd" in
  stop)
    if [ -f "$dir/data/postmaster.pid" ]; then pg pg_ctl -D "$dir/data" -m fast -w stop >&2; else say "not running in $dir"; fi
    exit 0;;
  url)
    [ -f "$dir/password" ] || die "no database in $dir: run \`bash deploy/prefect-db.sh start $dir\` first"
    url; exit 0;;
esac

if [ ! -f "$dir/data/PG_VERSION" ]; then
  umask 077
  head -c 18 /dev/urandom | base64 | tr '+/' '-_' > "$dir/password"
  echo "$port" > "$dir/port"
  [ -n "${as[*]}" ] && chown postgres: "$dir/password" "$dir/port"
  pg initdb -D "$dir/data" -U prefect --pwfile="$dir/password" --auth-local=scram-sha-256 --auth-host=scram-sha-256 \
    -E UTF8 --locale=C.UTF-8 >"$dir/initdb.log" 2>&1 || die "initdb failed: see $dir/initdb.log"
fi
if ! pg pg_ctl -D "$dir/data" status >/dev/null 2>&1; then
  pg pg_ctl -D "$dir/data" -l "$dir/server.log" -w -t 60 \
    -o "-c listen_addresses=127.0.0.1 -p $(cat "$dir/port") -c unix_socket_directories='$dir'" start >&2 \
    || die "PostgreSQL did not start: see $dir/server.log (is port $(cat "$dir/port") taken? remove $dir to start over on another)"
fi
export PGPASSWORD
PGPASSWORD=$(cat "$dir/password")
if ! "$bin/psql" -h 127.0.0.1 -p "$(cat "$dir/port")" -U prefect -d postgres -tAc "select 1 from pg_database where datname='prefect'" | grep -q 1; then
  "$bin/createdb" -h 127.0.0.1 -p "$(cat "$dir/port")" -U prefect prefect
fi
say "PostgreSQL for Prefect in $dir on 127.0.0.1:$(cat "$dir/port") (stop: bash deploy/prefect-db.sh stop $dir)"
url
