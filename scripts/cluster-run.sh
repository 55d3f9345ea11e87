#!/usr/bin/env bash
# The scale-out run (issue 17): a 3-node NATS JetStream cluster and 3 canopy-server edges on loopback
# (scripts/cluster.sh), and N headless bots (`canopy bots`) spread over the edges, the first K of them editing while
# all of them watch. Half-way through, one NATS node and one edge are killed with SIGKILL: the bots of the dead edge
# resume on the others, edits go on through the two NATS nodes left. The killed node is started again a few seconds
# later. At the end every edit the bots had acknowledged is read back from the JetStream stream (lost: not stored as
# acknowledged; duplicated: stored twice), every bot is checked against the world function + edits, and the last line
# printed is
#
#   edits acknowledged N, lost 0, duplicated 0, fan-out p50 X ms p99 Y ms, reconnects R
#
#   scripts/cluster-run.sh                          # 60 bots, 6 editing at 5 edits/s each, 40 s, kills at 20 s
#   COUNT=300 EDITING=10 EDIT_RATE=20 scripts/cluster-run.sh
#   COUNT=12 EDITING=6 EDIT_RATE=20 KILL_NATS=leader KILLS=10 KILL_AT=10 KILL_EVERY=5 DURATION=140 scripts/cluster-run.sh
#
# Environment: COUNT, EDITING (how many bots edit), EDIT_RATE (edits/s per editing bot), DURATION (s), KILL_AT (s
# after the bots start, when the edges are also reported; empty: never), RESTART_AFTER (s after the kill to start the
# NATS node again), KILL_NATS and KILL_EDGE (which ones; empty: none; KILL_NATS=leader: the node leading the edit
# stream at that moment), KILLS (how many times the NATS node is killed and started again, KILL_EVERY s apart after
# it is back; the edge dies once), PATH_KIND, SPEED, SPREAD (side of the square the bots stay in, m: bots on different
# edges hold the same cells), RADIUS, CONNECT_RATE, NATS_PORT, EDGE_PORT, CARGO_TARGET_DIR; EXTRA_BOTS_ARGS goes to
# `canopy bots` as is; KEEP=1 keeps the logs (edges', NATS nodes', bots'). Numbers and the machine they were measured on: docs/scale-out.md.
set -euo pipefail
cd "$(dirname "$0")/.."

COUNT=${COUNT:-60}
EDITING=${EDITING:-6}
EDIT_RATE=${EDIT_RATE:-5}
DURATION=${DURATION:-40}
KILL_AT=${KILL_AT-$((DURATION / 2))}
RESTART_AFTER=${RESTART_AFTER:-5}
KILL_NATS=${KILL_NATS-1}
KILL_EDGE=${KILL_EDGE-1}
KILLS=${KILLS:-1}
KILL_EVERY=${KILL_EVERY:-5}
PATH_KIND=${PATH_KIND:-random}
SPEED=${SPEED:-1}
SPREAD=${SPREAD:-64}
RADIUS=${RADIUS:-160}
CONNECT_RATE=${CONNECT_RATE:-50}
export NATS_PORT=${NATS_PORT:-14222}
export EDGE_PORT=${EDGE_PORT:-14433}
TARGET=${CARGO_TARGET_DIR:-target}
# shellcheck disable=SC2206
EXTRA=(${EXTRA_BOTS_ARGS:-})

cargo build --release -q -p canopy-server-app -p canopy-app
WORK=$(mktemp -d)
export CLUSTER_DIR="$WORK/cluster"
export CANOPY_SERVER="$TARGET/release/canopy-server"
BOTS=
cleanup() {
    [ -n "$BOTS" ] && kill "$BOTS" 2>/dev/null || true
    if [ -n "${KEEP:-}" ]; then
        # Keep the logs (edges', NATS nodes', the bots'); the processes still stop.
        for f in "$CLUSTER_DIR"/*.pid; do [ -f "$f" ] && kill "$(cat "$f")" 2>/dev/null || true; done
        echo "cluster-run: logs kept in $WORK" >&2
        return
    fi
    scripts/cluster.sh down >/dev/null 2>&1 || true
    rm -rf "$WORK"
}
trap cleanup EXIT

CANOPY_TOKEN=$("$CANOPY_SERVER" --editors "$WORK/editors" --add-editor bots --rate 100000 2>/dev/null)
export CANOPY_TOKEN
EDITORS="$WORK/editors" scripts/cluster.sh up 3 2>"$WORK/up.txt" >/dev/null || { cat "$WORK/up.txt" >&2; exit 1; }
FINGERPRINT=$(sed -n 's/^cluster: fingerprint //p' "$WORK/up.txt")
NATS_URLS=$(for i in 0 1 2; do printf 'nats://127.0.0.1:%d,' $((NATS_PORT + i)); done)
NATS_URLS=${NATS_URLS%,}
EDGES=$(for j in 0 1 2; do printf '127.0.0.1:%d,' $((EDGE_PORT + j)); done)
EDGES=${EDGES%,}
echo "cluster-run: 3 NATS nodes ($NATS_URLS), 3 edges ($EDGES); $COUNT bots, $EDITING editing at $EDIT_RATE edits/s" \
    "each, ${DURATION} s, path $PATH_KIND at $SPEED m/s in a ${SPREAD} m square; kill NATS node $KILL_NATS" \
    "($KILLS times) and edge $KILL_EDGE at ${KILL_AT:-never} s; bots and edges share this machine's $(nproc) cores"

# One line per edge alive: clients now, edits acknowledged, cells watched, edits in from the engine, the engine's
# round trip, reconnects to NATS, RSS and CPU seconds so far.
TICKS=$(getconf CLK_TCK)
edges_report() {
    for j in 0 1 2; do
        m=$(curl -s "http://127.0.0.1:$((EDGE_PORT + 1000 + j))/metrics" 2>/dev/null) || { echo "edge $j: down"; continue; }
        cpu=$(awk -v t="$TICKS" '{ printf "%.1f", ($14 + $15) / t }' "/proc/$(cat "$CLUSTER_DIR/edge-$j.pid")/stat" 2>/dev/null || echo "?")
        echo "$m" | awk -v j="$j" -v cpu="$cpu" '
            $1 == "canopy_clients" { clients = $2 }
            $1 ~ /^canopy_edits_total\{outcome="ok"/ { ok = $2 }
            $1 == "canopy_engine_watched_cells" { watched = $2 }
            $1 == "canopy_engine_deltas_in_total" { din = $2 }
            $1 == "canopy_engine_reconnects_total" { rec = $2 }
            $1 == "canopy_engine_round_trip_seconds_count" { n = $2 }
            $1 == "canopy_engine_round_trip_seconds_sum" { sum = $2 }
            $1 == "canopy_resident_bytes" { rss = $2 }
            END {
                printf "edge %d: %d clients, %d edits acknowledged, %d cells watched, %d edits in from the engine, ", j, clients, ok, watched, din
                printf "engine round trip mean %.2f ms over %d calls, %d NATS reconnects, RSS %.1f MiB, CPU %s s\n", (n > 0 ? 1000 * sum / n : 0), n, rec, rss / 1048576, cpu
            }'
    done
}

"$TARGET/release/canopy" bots --count "$COUNT" --editors "$EDITING" --edit-rate "$EDIT_RATE" --path "$PATH_KIND" \
    --speed "$SPEED" --duration "$DURATION" --radius "$RADIUS" --connect-rate "$CONNECT_RATE" --spread "$SPREAD" \
    --server "$EDGES" --cert-fingerprint "$FINGERPRINT" --check-edits "$NATS_URLS" --quiet "${EXTRA[@]}" \
    >"$WORK/bots.txt" 2>"$WORK/bots.err" &
BOTS=$!
START=$(date +%s.%N)

if [ -n "$KILL_AT" ]; then
    sleep "$KILL_AT"
    echo "---- edges at ${KILL_AT} s, before the kill"
    edges_report
    [ -n "$KILL_EDGE" ] && scripts/cluster.sh kill edge "$KILL_EDGE"
    for ((k = 1; k <= KILLS; k++)); do
        [ -n "$KILL_NATS" ] || break
        [ "$k" -gt 1 ] && sleep "$KILL_EVERY"
        NODE=$KILL_NATS
        [ "$NODE" = leader ] && NODE=$(scripts/cluster.sh leader)
        scripts/cluster.sh kill nats "$NODE"
        KILLED=$(date +%s.%N)
        sleep "$RESTART_AFTER"
        scripts/cluster.sh start nats "$NODE"
        awk -v a="$KILLED" -v b="$(date +%s.%N)" -v k="$k" -v n="$NODE" \
            'BEGIN { printf "cluster-run: kill %d: NATS node %s started again %.1f s after the kill\n", k, n, b - a }'
    done
fi

set +e
wait "$BOTS"
BOTS_STATUS=$?
BOTS=
set -e
END=$(date +%s.%N)
echo "---- edges at the end (the ones alive)"
edges_report
# The edit bus: bytes the NATS nodes received and sent (clients and routes: publishes, acknowledgements, replication,
# watches, API calls, heartbeats) over the run, per acknowledged edit below.
BUS=0
for i in 0 1 2; do
    b=$(curl -s "http://127.0.0.1:$((NATS_PORT + 200 + i))/varz" 2>/dev/null | python3 -c 'import json,sys; v=json.load(sys.stdin); print(v["in_bytes"] + v["out_bytes"])' 2>/dev/null || echo 0)
    BUS=$((BUS + b))
done
echo "---- bots"
cat "$WORK/bots.txt"
if [ "$BOTS_STATUS" -ne 0 ] && [ ! -s "$WORK/bots.txt" ]; then
    cat "$WORK/bots.err" >&2
fi
awk -v a="$START" -v b="$END" 'BEGIN { printf "bots process wall time %.1f s\n", b - a }'
LINE=$(grep '^edits acknowledged ' "$WORK/bots.txt" | tail -1 || true)
if [ -z "$LINE" ]; then
    echo "cluster-run: the bots printed no ledger line" >&2
    exit 1
fi
ACKED=$(echo "$LINE" | sed -n 's/^edits acknowledged \([0-9]*\),.*/\1/p')
awk -v b="$BUS" -v n="$ACKED" 'BEGIN { printf "edit bus: %.1f MB in and out of the NATS nodes alive at the end (since their start), %.0f B per acknowledged edit\n", b / 1e6, (n > 0 ? b / n : 0) }'
echo "$LINE"
exit "$BOTS_STATUS"
