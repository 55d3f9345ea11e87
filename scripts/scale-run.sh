#!/usr/bin/env bash
# One server over its cores: scripts/load-run.sh once per core count, the server pinned (`taskset`) to that many
# cores with as many endpoints (UDP sockets on its port), the bots in several processes on cores of their own; then a
# line a step: bots complete and failed, AOI change → complete p99, connect → first complete p99, the server's CPU
# (cores busy, seconds per thousand client-seconds), its memory per client, and its throughput (records sent a second
# of the bots' run: with `EXTRA_BOTS_ARGS=--records` the bots take every record from the server, its heaviest load).
#
#   scripts/scale-run.sh                                  # 1 and 2 cores, 2,000 bots: what a 2-core machine shows
#   CORES="1 2 4 8" BOTS_CORES=8-15 COUNT=10000 PROCESSES=8 scripts/scale-run.sh      # a 16-core machine
#
# Environment: CORES (the core counts, cores 0..k-1 each), ENDPOINTS (default: as many as cores), BOTS_CORES (`taskset -c` list; default: unpinned),
# COUNT, DURATION, CONNECT_RATE, PROCESSES, SETTLE (s a bot waits at the end), BIN (prebuilt binaries, as for
# load-run.sh), LOG (a file every step's whole output is appended to); the rest goes to load-run.sh as is.
set -euo pipefail
cd "$(dirname "$0")/.."

CORES=${CORES:-1 2}
COUNT=${COUNT:-2000}
DURATION=${DURATION:-20}
CONNECT_RATE=${CONNECT_RATE:-1000}
PROCESSES=${PROCESSES:-2}
SETTLE=${SETTLE:-30}
LOG=${LOG:-$(mktemp)}

printf '%-6s %-9s %-8s %-6s %-12s %-14s %-11s %-15s %-12s %-10s\n' cores endpoints complete failed "AOI p99 ms" \
    "first p99 ms" "server CPU" "CPU s/1k cl-s" "KiB/client" "records/s"
for k in $CORES; do
    out=$(mktemp)
    set +e
    SERVER_CORES="0-$((k - 1))" ENDPOINTS="${ENDPOINTS:-$k}" COUNT="$COUNT" DURATION="$DURATION" CONNECT_RATE="$CONNECT_RATE" \
        PROCESSES="$PROCESSES" EXTRA_SERVER_ARGS="--max-clients 200000 --max-per-source 200000 ${EXTRA_SERVER_ARGS:-}" \
        EXTRA_BOTS_ARGS="--settle $SETTLE --endpoints 16 ${EXTRA_BOTS_ARGS:-}" scripts/load-run.sh >"$out" 2>&1
    status=$?
    set -e
    { echo "==== $k cores (exit $status)"; cat "$out"; } >>"$LOG"
    awk -v k="$k" -v e="${ENDPOINTS:-$k}" -v st="$status" '
        /^bots: / { complete = $4; failed = $9 }
        /^AOI change → complete/ { for (i = 1; i <= NF; i++) if ($i == "p99") p99 = $(i + 1) }
        /^connect → first complete/ { for (i = 1; i <= NF; i++) if ($i == "p99") first = $(i + 1) }
        /^server CPU while/ { cores = $(NF - 1); sub(/\(/, "", cores) }
        /^server CPU per thousand/ { per = $(NF - 1) }
        /^server memory:/ { kib = $(NF - 3) }
        /^sessions [0-9]+; records sent/ { records = $5; sub(/;/, "", records) }
        /^bots process wall time/ { wall = $(NF - 1) }
        END {
            rate = (wall > 0) ? records / wall : 0
            printf "%-6s %-9s %-8s %-6s %-12s %-14s %-11s %-15s %-12s %-10.0f%s\n", k, e, complete, failed, p99, first,
                cores, per, kib, rate, (st == 0 ? "" : "  (bots exit " st ")")
        }' "$out"
    rm -f "$out"
done
echo "every step's whole output: $LOG"
