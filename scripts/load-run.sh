#!/usr/bin/env bash
# The streaming load run: canopy-server (release) on the embedded default world in one process, N headless bots
# (`canopy bots`) in another, over QUIC on loopback. Prints the bots' summary (every bot ends with a complete area of
# interest checked against the world; AOI change → complete latency percentiles; bytes per record) and the server's
# side: bytes per record by message class from its metrics, and server memory per client (VmRSS with all bots
# connected minus VmRSS before the first client, divided by the clients).
#
#   scripts/load-run.sh                      # 1,000 bots, random walks at 5 m/s for 30 s
#   COUNT=10000 DURATION=60 scripts/load-run.sh
#   COUNT=20 DURATION=10 scripts/load-run.sh # the CI-sized version
#   WORLD=worlds/highlands/highlands.world COUNT=1000 scripts/load-run.sh   # bots spread over the large world
#   COUNT=50000 PROCESSES=8 SERVER_CORES=0-7 BOTS_CORES=8-15 scripts/load-run.sh   # a many-core server
#
# Environment: COUNT, DURATION (s), PATH_KIND (line|circle|random|teleport|…), SPEED (m/s), RADIUS (m),
# CONNECT_RATE (bots/s), TICK_MS (how often a bot moves), WORLD (a manifest; default: the embedded default world),
# CELL_CACHE_MIB, PORT, METRICS_PORT, CARGO_TARGET_DIR, AFTER (s: the server's memory that long after the bots
# left); EXTRA_BOTS_ARGS is passed to `canopy bots` as is, EXTRA_SERVER_ARGS to `canopy-server` (all bots come from
# one address: past 4,096 of them, `--max-per-source`). For many cores: ENDPOINTS (the server's UDP sockets; default
# one per core it may use), PROCESSES (bot processes), SERVER_CORES and BOTS_CORES (`taskset -c` lists: the server's
# cores and the bots' apart, so neither is measured starved by the other), BIN (a folder holding release
# `canopy-server` and `canopy` built beforehand: nothing is built).
set -euo pipefail
cd "$(dirname "$0")/.."

COUNT=${COUNT:-1000}
DURATION=${DURATION:-30}
PATH_KIND=${PATH_KIND:-random}
SPEED=${SPEED:-5}
RADIUS=${RADIUS:-160}
CONNECT_RATE=${CONNECT_RATE:-100}
TICK_MS=${TICK_MS:-100}
PORT=${PORT:-4433}
METRICS_PORT=${METRICS_PORT:-9433}
TARGET=${CARGO_TARGET_DIR:-target}
WORLD=${WORLD:-}
CELL_CACHE_MIB=${CELL_CACHE_MIB:-256}
PROCESSES=${PROCESSES:-1}
ENDPOINTS=${ENDPOINTS:-0}
BIN=${BIN:-}
PIN_SERVER=()
[ -n "${SERVER_CORES:-}" ] && PIN_SERVER=(taskset -c "$SERVER_CORES")
PIN_BOTS=()
[ -n "${BOTS_CORES:-}" ] && PIN_BOTS=(taskset -c "$BOTS_CORES")
WORLD_ARGS=()
[ -n "$WORLD" ] && WORLD_ARGS=(--world "$WORLD")
# shellcheck disable=SC2206
SERVER_ARGS=(${EXTRA_SERVER_ARGS:-})
# shellcheck disable=SC2206
EXTRA=(${EXTRA_BOTS_ARGS:-})

if [ -z "$BIN" ]; then
    cargo build --release -q -p canopy-server-app -p canopy-app
    BIN="$TARGET/release"
fi
WORK=$(mktemp -d)
SERVER_LOG="$WORK/server.log"

"${PIN_SERVER[@]}" "$BIN/canopy-server" --listen "127.0.0.1:$PORT" --metrics "127.0.0.1:$METRICS_PORT" \
    --endpoints "$ENDPOINTS" --data-dir "$WORK/data" --stats-every 5 --cell-cache-mib "$CELL_CACHE_MIB" "${WORLD_ARGS[@]}" "${SERVER_ARGS[@]}" >"$SERVER_LOG" 2>&1 &
SERVER=$!
trap 'kill "$SERVER" 2>/dev/null || true; wait "$SERVER" 2>/dev/null || true' EXIT

for _ in $(seq 1 300); do
    grep -q '^fingerprint ' "$SERVER_LOG" && break
    kill -0 "$SERVER" 2>/dev/null || { cat "$SERVER_LOG"; echo "load-run: the server died" >&2; exit 1; }
    sleep 0.2
done
FINGERPRINT=$(awk '/^fingerprint /{print $2}' "$SERVER_LOG")
[ -n "$FINGERPRINT" ] || { cat "$SERVER_LOG"; echo "load-run: no fingerprint" >&2; exit 1; }
rss_kib() { awk '/^VmRSS:/{print $2}' "/proc/$SERVER/status"; }
# The metrics page over bash's own TCP (no curl needed).
scrape() {
    exec 3<>"/dev/tcp/127.0.0.1/$METRICS_PORT" || return 0
    printf 'GET /metrics HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n' >&3
    cat <&3
    exec 3<&-
}
metric() { scrape | awk -v m="$1" '$1==m{print $2}'; }
# The baseline once the world's start has settled (memory freed at start goes back to the OS over seconds).
RSS0=$(rss_kib)
for _ in $(seq 1 15); do
    sleep 1
    r=$(rss_kib)
    [ $((r > RSS0 ? r - RSS0 : RSS0 - r)) -lt 1024 ] && { RSS0=$r; break; }
    RSS0=$r
done
echo "load-run: server pid $SERVER, world loaded, VmRSS ${RSS0} KiB before any client"
grep -E '^(listening on|socket buffers)|granted UDP buffers' "$SERVER_LOG" || true

# Sample the server's memory and clients while the bots run; keep the sample with the most clients.
(
    best_clients=0
    while kill -0 "$SERVER" 2>/dev/null; do
        c=$(metric canopy_clients || echo 0)
        r=$(rss_kib || echo 0)
        if [ -n "$c" ] && [ "$c" -ge "$best_clients" ]; then
            best_clients=$c
            echo "$c $r" >"$WORK/peak"
        fi
        sleep 1
    done
) &
SAMPLER=$!

cpu_ticks() { awk '{print $14 + $15}' "/proc/$SERVER/stat"; }
CPU0=$(cpu_ticks)
START=$(date +%s.%N)
set +e
"${PIN_BOTS[@]}" "$BIN/canopy" bots --processes "$PROCESSES" --count "$COUNT" --path "$PATH_KIND" --speed "$SPEED" --duration "$DURATION" \
    --radius "$RADIUS" --connect-rate "$CONNECT_RATE" --tick-ms "$TICK_MS" --server "127.0.0.1:$PORT" \
    --cert-fingerprint "$FINGERPRINT" --quiet "${WORLD_ARGS[@]}" "${EXTRA[@]}"
BOTS_STATUS=$?
set -e
END=$(date +%s.%N)
CPU1=$(cpu_ticks)
sleep 1.5
kill "$SAMPLER" 2>/dev/null || true

read -r PEAK_CLIENTS PEAK_RSS <"$WORK/peak" || true
CELLS=$(metric 'canopy_sent_bytes_total{class="cells"}')
SPECIES=$(metric 'canopy_sent_bytes_total{class="species"}')
RELEASES=$(metric 'canopy_sent_bytes_total{class="release"}')
WELCOME=$(metric 'canopy_sent_bytes_total{class="welcome"}')
RECORDS=$(metric canopy_records_sent_total)
GRANTS=$(metric 'canopy_sent_messages_total{class="grant"}')
GRANT_BYTES=$(metric 'canopy_sent_bytes_total{class="grant"}')
SPECIES_MSGS=$(metric 'canopy_sent_messages_total{class="species"}')
SESSIONS=$(metric canopy_sessions_total)
echo "---- server side"
awk -v c="$CELLS" -v s="$SPECIES" -v rl="$RELEASES" -v w="$WELCOME" -v r="$RECORDS" -v sm="$SPECIES_MSGS" -v n="$SESSIONS" 'BEGIN {
    printf "sessions %d; records sent %d; species sent %d times (%.1f per session)\n", n, r, sm, sm / (n > 0 ? n : 1);
    if (r > 0) printf "bytes per record: %.2f in cell batches; %.2f with species, releases and welcomes (frames, before QUIC)\n", c / r, (c + s + rl + w) / r;
}'
awk -v r0="$RSS0" -v r1="$PEAK_RSS" -v c="$PEAK_CLIENTS" 'BEGIN {
    printf "server memory: VmRSS %.1f MiB before clients, %.1f MiB with %d clients: %.1f KiB per client\n", r0 / 1024, r1 / 1024, c, (r1 - r0) / (c > 0 ? c : 1);
}'
echo "cell cache: hits $(metric canopy_cell_cache_hits_total), misses $(metric canopy_cell_cache_misses_total), expansions $(metric canopy_cell_expansions_total) (p50 $(metric canopy_cell_expansion_p50_microseconds) µs, p99 $(metric canopy_cell_expansion_p99_microseconds) µs), $(metric canopy_cell_cache_cells) cells in $(metric canopy_cell_cache_bytes) bytes, $(metric canopy_cell_evictions_total) evicted"
awk -v a="$START" -v b="$END" 'BEGIN { printf "bots process wall time %.1f s\n", b - a }'
echo "grants (cells the clients expanded themselves): ${GRANTS:-0} in ${GRANT_BYTES:-0} bytes"
SENT=$(scrape | awk '$1 ~ /^canopy_sent_bytes_total/ {s += $2} END {print s + 0}')
awk -v b="$SENT" -v n="$SESSIONS" -v d="$DURATION" 'BEGIN {
    printf "server sent %.1f MiB (frames): %.1f KiB a session, %.0f B a session a second of the walk\n", b / 1048576, b / 1024 / (n > 0 ? n : 1), b / (n > 0 ? n : 1) / d;
}'
awk -v t0="$CPU0" -v t1="$CPU1" -v hz="$(getconf CLK_TCK)" -v a="$START" -v b="$END" 'BEGIN {
    printf "server CPU while the bots ran: %.1f s in %.1f s of wall time (%.2f cores)\n", (t1 - t0) / hz, b - a, (t1 - t0) / hz / (b - a);
}'
awk -v t0="$CPU0" -v t1="$CPU1" -v hz="$(getconf CLK_TCK)" -v n="$COUNT" -v d="$DURATION" 'BEGIN {
    printf "server CPU per thousand client-seconds of the walk: %.3f s\n", (t1 - t0) / hz / (n * d / 1000);
}'
echo "server peak memory: VmHWM $(awk '/^VmHWM:/{print $2}' "/proc/$SERVER/status") KiB; endpoints: $(scrape | grep -c '^canopy_endpoint_clients{')"
grep -E "stats" "$SERVER_LOG" | tail -n 3 || true
if [ -n "${AFTER:-}" ]; then
    sleep "$AFTER"
    awk -v r0="$RSS0" -v r1="$(rss_kib)" -v a="$AFTER" -v q="$(metric canopy_cell_expansions_queued)" 'BEGIN {
        printf "%s s after the bots left: VmRSS %.1f MiB (%.1f MiB before any client), %d cells still queued\n", a, r1 / 1024, r0 / 1024, q;
    }'
fi
exit "$BOTS_STATUS"
