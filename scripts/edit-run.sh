#!/usr/bin/env bash
# The live-edit run: canopy-server (release) on the embedded default world with its edits in a temporary data
# directory (SQLite, group commit) and one editor of a high rate, and N headless bots (`canopy bots`) in another
# process standing together in a small square around the middle of the world, the first K of them editing (plants
# near them, every third edit a fell of one of their own plants) while all of them watch. Prints the bots' summary —
# edits sent and answered by outcome, send → answer latency, edit fan-out (send → visible on the other bots holding
# the cell, per bot and per edit), the check against the world and between bots — then restarts the server on the
# same data directory and compares the edits it finds stored with the edits acknowledged.
#
#   scripts/edit-run.sh                                           # 100 bots, 2 editing at 5 edits/s each, 30 s
#   EDITORS=5 EDIT_RATE=50 scripts/edit-run.sh                    # 5 of the 100 editing at 50 edits/s each
#   SPREAD= COUNT=20 EDITORS=20 EDIT_RATE=1000 scripts/edit-run.sh  # throughput: 20 editors over the whole world
#
# Numbers and the machine they were measured on: docs/edits.md ("Numbers").
#
# Environment: COUNT, EDITORS (how many bots edit), EDIT_RATE (edits/s per editing bot), DURATION (s), PATH_KIND,
# SPEED (m/s), SPREAD (side of the square the bots stay in, m; empty: the whole world), RADIUS (m), EDITOR_RATE (the
# editor's rate in the editors file, shared by all editing bots), CONNECT_RATE, PORT, METRICS_PORT,
# CARGO_TARGET_DIR; EXTRA_BOTS_ARGS is passed to `canopy bots` as is.
set -euo pipefail
cd "$(dirname "$0")/.."

COUNT=${COUNT:-100}
EDITORS=${EDITORS:-2}
EDIT_RATE=${EDIT_RATE:-5}
DURATION=${DURATION:-30}
PATH_KIND=${PATH_KIND:-random}
SPEED=${SPEED:-1}
SPREAD=${SPREAD-32}
RADIUS=${RADIUS:-160}
EDITOR_RATE=${EDITOR_RATE:-100000}
CONNECT_RATE=${CONNECT_RATE:-100}
PORT=${PORT:-4433}
METRICS_PORT=${METRICS_PORT:-9433}
TARGET=${CARGO_TARGET_DIR:-target}
SPREAD_ARGS=()
[ -n "$SPREAD" ] && SPREAD_ARGS=(--spread "$SPREAD")
# shellcheck disable=SC2206
EXTRA=(${EXTRA_BOTS_ARGS:-})

cargo build --release -q -p canopy-server-app -p canopy-app
WORK=$(mktemp -d)
SERVER=
cleanup() {
    if [ -n "$SERVER" ]; then
        kill "$SERVER" 2>/dev/null || true
        wait "$SERVER" 2>/dev/null || true
    fi
    rm -rf "$WORK"
}
trap cleanup EXIT

# Starts the server on the data directory in the background, waits for its fingerprint line; sets SERVER.
start_server() {
    local log=$1
    "$TARGET/release/canopy-server" --listen "127.0.0.1:$PORT" --metrics "127.0.0.1:$METRICS_PORT" \
        --data-dir "$WORK/data" --editors "$WORK/editors" --stats-every 5 >"$log" 2>&1 &
    SERVER=$!
    for _ in $(seq 1 300); do
        grep -q '^fingerprint ' "$log" && return 0
        kill -0 "$SERVER" 2>/dev/null || { cat "$log"; echo "edit-run: the server died" >&2; exit 1; }
        sleep 0.2
    done
    cat "$log"
    echo "edit-run: no fingerprint" >&2
    exit 1
}

# Stops the server as Ctrl-C does (it writes what is queued and closes the store).
stop_server() {
    kill -INT "$SERVER" 2>/dev/null || true
    wait "$SERVER" 2>/dev/null || true
    SERVER=
}

CANOPY_TOKEN=$("$TARGET/release/canopy-server" --editors "$WORK/editors" --add-editor bots --rate "$EDITOR_RATE" 2>/dev/null)
export CANOPY_TOKEN
start_server "$WORK/server.log"
FINGERPRINT=$(awk '/^fingerprint /{print $2}' "$WORK/server.log")
echo "edit-run: server pid $SERVER; $COUNT bots, $EDITORS editing at $EDIT_RATE edits/s each, ${DURATION} s," \
    "path $PATH_KIND at $SPEED m/s, spread ${SPREAD:-whole world} m, radius $RADIUS m"

START=$(date +%s.%N)
set +e
"$TARGET/release/canopy" bots --count "$COUNT" --editors "$EDITORS" --edit-rate "$EDIT_RATE" --path "$PATH_KIND" \
    --speed "$SPEED" --duration "$DURATION" --radius "$RADIUS" --connect-rate "$CONNECT_RATE" "${SPREAD_ARGS[@]}" \
    --server "127.0.0.1:$PORT" --cert-fingerprint "$FINGERPRINT" --quiet "${EXTRA[@]}" | tee "$WORK/bots.txt"
BOTS_STATUS=${PIPESTATUS[0]}
set -e
END=$(date +%s.%N)
echo "---- server side"
metrics() { curl -s "http://127.0.0.1:$METRICS_PORT/metrics" || true; }
metrics >"$WORK/metrics.txt"
# Edits answered by outcome, groups written (group commit), and the commit time's histogram (bucket upper bounds).
awk '
    $1 ~ /^canopy_edits_total\{/ { split($1, a, "\""); out = out sprintf(" %s %d", a[2], $2) }
    $1 == "canopy_edit_groups_total" { groups = $2 }
    $1 ~ /^canopy_edit_commit_seconds_bucket/ { split($1, a, "\""); le[n] = a[2]; cum[n] = $2; n++ }
    $1 == "canopy_edit_commit_seconds_count" { count = $2 }
    $1 == "canopy_edit_commit_seconds_sum" { sum = $2 }
    END {
        if (groups == "") { print "server: no edit metrics"; exit }
        q50 = q99 = "";
        for (i = 0; i < n; i++) {
            if (q50 == "" && cum[i] >= 0.5 * count) q50 = le[i];
            if (q99 == "" && cum[i] >= 0.99 * count) q99 = le[i];
        }
        printf "server: edits answered:%s; %d groups written (%.1f acknowledged edits a group)\n", out, groups, (groups > 0 ? ok_edits(out) / groups : 0);
        printf "server: group commit time (first edit queued → durable) mean %.2f ms, p50 ≤ %s s, p99 ≤ %s s\n", (count > 0 ? 1000 * sum / count : 0), q50, q99;
    }
    function ok_edits(s,   a) { split(s, a, " "); return a[2] }
' "$WORK/metrics.txt"
sed "s/\x1b\[[0-9;]*m//g" "$WORK/server.log" | grep -E "stats" | tail -n 2 || true
awk -v a="$START" -v b="$END" 'BEGIN { printf "bots process wall time %.1f s\n", b - a }'

# Durability: the edits stored are the edits acknowledged (every acknowledged edit was written before its answer).
stop_server
start_server "$WORK/restart.log"
STORED=$(awk '/ edits stored in /{print $1}' "$WORK/restart.log")
ACKED=$(sed -n 's/.* sent ([0-9]* plants, [0-9]* fells), \([0-9]*\) acknowledged.*/\1/p' "$WORK/bots.txt")
UNANSWERED=$(sed -n 's/.* conflicts, \([0-9]*\) unanswered.*/\1/p' "$WORK/bots.txt")
echo "after a restart: $STORED edits stored; ${ACKED:-?} acknowledged by the bots, ${UNANSWERED:-?} unanswered"
# An edit stored whose answer the bot did not wait for is unanswered, not lost.
if [ -n "$ACKED" ] && { [ "$STORED" -lt "$ACKED" ] || [ "$STORED" -gt $((ACKED + ${UNANSWERED:-0})) ]; }; then
    echo "edit-run: the store holds $STORED edits, the bots saw $ACKED acknowledged" >&2
    exit 1
fi
stop_server
exit "$BOTS_STATUS"
