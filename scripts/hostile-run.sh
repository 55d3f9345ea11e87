#!/usr/bin/env bash
# The hardening numbers of issue 14: `canopy-server` (release, default flags) on the embedded default world, a fresh
# server per scenario, attacked on loopback by the harness's `hostile` example. For each scenario the server's VmRSS
# (/proc/PID/status) is read before, during and after, and its metrics endpoint around it; one summary line each:
#
#   nonack   COUNT clients that never acknowledge (a UDP relay black-holes server → client after the welcome), each
#            asking for a radius-512 area and teleporting 3 times, hanging HOLD s, then vanishing: VmRSS before,
#            with them and after the server's idle timeout let them go (with the cell cache's bytes, which belong
#            to the world, not to the clients); send data pinned per connection. NONACK_ROUNDS rounds on one server
#            (the second with the cache and the allocator warm).
#   flood    a half-open handshake flood (real Initials, never followed up) at FLOOD_RATE/s for FLOOD_DURATION s from
#            256 loopback addresses while BOTS legitimate bots connect: the fraction admitted.
#   vpflood  one client sending viewpoints (teleports, radius 512) as fast as it can, then at VP_RATE/s, for
#            VP_DURATION s each: the server's egress bytes per viewpoint byte.
#
#   scripts/hostile-run.sh                          # all three, the sizes of issue 14
#   SCENARIOS="nonack" COUNT=100 HOLD=10 scripts/hostile-run.sh
#
# Environment: SCENARIOS, COUNT, NONACK_ROUNDS, HOLD (s), FLOOD_RATE (/s), FLOOD_DURATION (s), BOTS, VP_RATE (/s), VP_DURATION (s),
# PORT, METRICS_PORT, CARGO_TARGET_DIR; EXTRA_SERVER_ARGS is passed to canopy-server as is.
set -euo pipefail
cd "$(dirname "$0")/.."

SCENARIOS=${SCENARIOS:-nonack flood vpflood}
COUNT=${COUNT:-300}
NONACK_ROUNDS=${NONACK_ROUNDS:-2}
HOLD=${HOLD:-15}
FLOOD_RATE=${FLOOD_RATE:-1000}
FLOOD_DURATION=${FLOOD_DURATION:-20}
BOTS=${BOTS:-20}
VP_RATE=${VP_RATE:-50}
VP_DURATION=${VP_DURATION:-20}
PORT=${PORT:-4473}
METRICS_PORT=${METRICS_PORT:-9473}
TARGET=${CARGO_TARGET_DIR:-target}
# shellcheck disable=SC2206
EXTRA=(${EXTRA_SERVER_ARGS:-})

cargo build --release -q -p canopy-server-app
cargo build --release -q -p canopy-harness --example hostile
HOSTILE="$TARGET/release/examples/hostile"
WORK=$(mktemp -d)
SERVER=
ATTACK=
cleanup() {
    [ -n "$ATTACK" ] && kill "$ATTACK" 2>/dev/null || true
    [ -n "$SERVER" ] && kill "$SERVER" 2>/dev/null || true
    [ -n "$SERVER" ] && wait "$SERVER" 2>/dev/null || true
    rm -rf "$WORK"
}
trap cleanup EXIT

rss_kib() { awk '/^VmRSS:/{print $2}' "/proc/$SERVER/status"; }
metrics() { curl -s --max-time 5 "http://127.0.0.1:$METRICS_PORT/metrics"; }
metric() { metrics | awk -v m="$1" '$1==m{print $2}'; }
sent_total() { metrics | awk '$1 ~ /^canopy_sent_bytes_total\{/ {s += $2} END {printf "%d\n", s}'; }
mib() { awk -v k="$1" 'BEGIN { printf "%.1f", k / 1024 }'; }

start_server() {
    "$TARGET/release/canopy-server" --listen "127.0.0.1:$PORT" --metrics "127.0.0.1:$METRICS_PORT" \
        --data-dir "$WORK/data" --stats-every 0 "${EXTRA[@]}" >"$WORK/server.log" 2>&1 &
    SERVER=$!
    for _ in $(seq 1 300); do
        grep -q '^fingerprint ' "$WORK/server.log" && break
        kill -0 "$SERVER" 2>/dev/null || { cat "$WORK/server.log"; echo "hostile-run: the server died" >&2; exit 1; }
        sleep 0.2
    done
    FINGERPRINT=$(awk '/^fingerprint /{print $2}' "$WORK/server.log")
    [ -n "$FINGERPRINT" ] || { cat "$WORK/server.log"; echo "hostile-run: no fingerprint" >&2; exit 1; }
    sleep 1
}

stop_server() {
    kill "$SERVER" 2>/dev/null || true
    wait "$SERVER" 2>/dev/null || true
    SERVER=
}

# Wait (up to $2 s) until the attack's log has a line starting with $1.
wait_line() {
    for _ in $(seq 1 $(($2 * 5))); do
        grep -q "^$1" "$WORK/attack.log" && return 0
        kill -0 "$ATTACK" 2>/dev/null || return 1
        sleep 0.2
    done
    return 1
}

SUMMARY=()

# One round of clients that never acknowledge against the running server.
nonack_round() {
    local rss0 cache0 rss_peak=0 clients_peak=0 sent_peak=0 cache_peak=0 sent0 read rss_after cache_after clients
    local r c s k waited=0
    rss0=$(rss_kib); cache0=$(metric canopy_cell_cache_bytes); sent0=$(sent_total)
    "$HOSTILE" nonack --server "127.0.0.1:$PORT" --fingerprint "$FINGERPRINT" --count "$COUNT" --hold "$HOLD" \
        >"$WORK/attack.log" 2>&1 &
    ATTACK=$!
    wait_line hanging 300 || { cat "$WORK/attack.log"; echo "hostile-run: the clients never hung" >&2; exit 1; }
    read=$(awk '/^hanging/{print ($NF == "B" ? $(NF-1) : 0)}' "$WORK/attack.log")
    while kill -0 "$ATTACK" 2>/dev/null; do
        r=$(rss_kib); c=$(metric canopy_clients); s=$(sent_total); k=$(metric canopy_cell_cache_bytes)
        [ "${r:-0}" -gt "$rss_peak" ] && rss_peak=$r
        [ "${c:-0}" -gt "$clients_peak" ] && clients_peak=$c
        [ "${s:-0}" -gt "$sent_peak" ] && sent_peak=$s
        [ "${k:-0}" -gt "$cache_peak" ] && cache_peak=$k
        sleep 1
    done
    wait "$ATTACK" || true
    ATTACK=
    cat "$WORK/attack.log"
    # They vanished: the server forgets them after its idle timeout (30 s).
    while [ "$(metric canopy_clients)" != 0 ] && [ "$waited" -lt 180 ]; do
        sleep 1
        waited=$((waited + 1))
    done
    clients=$(metric canopy_clients)
    sleep 2
    rss_after=$(rss_kib); cache_after=$(metric canopy_cell_cache_bytes)
    local line
    line=$(awk -v round="$1" -v n="$COUNT" -v peak="$clients_peak" -v r0="$rss0" -v r1="$rss_peak" \
        -v r2="$rss_after" -v k0="$cache0" -v k1="$cache_peak" -v k2="$cache_after" -v sent="$((sent_peak - sent0))" \
        -v read="$read" -v c="$clients" -v w="$waited" 'BEGIN {
        goal = 64 * 1024 + 300 * n; p = peak > 0 ? peak : 1;
        printf "nonack round %d: %d clients that never acknowledge (%d connected at the peak): VmRSS %.1f MiB before, %.1f MiB with them (goal <= 64 MiB + 300 KiB each = %.1f MiB: %s), %.1f MiB after they left (%d clients left %d s after the relays stopped); per client %.1f KiB of VmRSS, %.1f KiB without the cell cache'"'"'s growth (cell cache %.1f -> %.1f -> %.1f MiB); send data pinned per connection (sent - read) %.1f KiB",
            round, n, peak, r0 / 1024, r1 / 1024, goal / 1024, (r1 <= goal ? "met" : "MISSED"), r2 / 1024, c, w,
            (r1 - r0) / p, (r1 - r0 - (k1 - k0) / 1024) / p, k0 / 1048576, k1 / 1048576, k2 / 1048576,
            (sent - read) / p / 1024;
    }')
    echo "$line"
    SUMMARY+=("$line")
}

# Round 1 on a fresh server; round 2 on the same server, its cell cache and allocator already warm.
scenario_nonack() {
    start_server
    for round in $(seq 1 "$NONACK_ROUNDS"); do
        nonack_round "$round"
    done
    stop_server
}

scenario_flood() {
    start_server
    local rss0 rss_peak=0 hs_peak=0 r h result
    rss0=$(rss_kib)
    "$HOSTILE" flood --server "127.0.0.1:$PORT" --fingerprint "$FINGERPRINT" --rate "$FLOOD_RATE" \
        --duration "$FLOOD_DURATION" --bots "$BOTS" >"$WORK/attack.log" 2>&1 &
    ATTACK=$!
    while kill -0 "$ATTACK" 2>/dev/null; do
        r=$(rss_kib); h=$(metric canopy_handshakes)
        [ "${r:-0}" -gt "$rss_peak" ] && rss_peak=$r
        [ "${h:-0}" -gt "$hs_peak" ] && hs_peak=$h
        sleep 1
    done
    wait "$ATTACK" || true
    ATTACK=
    cat "$WORK/attack.log"
    result=$(grep '^flood: .* Initials (' "$WORK/attack.log" | sed 's/^flood: //')
    local line
    line="flood: $result; server: $(metric canopy_retries_total) Retries, refused $(metric 'canopy_refused_total{reason="full"}') full / $(metric 'canopy_refused_total{reason="busy"}') busy / $(metric 'canopy_refused_total{reason="per_source"}') per source, at most $hs_peak handshakes in flight, $(metric canopy_sessions_total) sessions; VmRSS $(mib "$rss0") MiB before, $(mib "$rss_peak") MiB at the peak"
    echo "$line"
    SUMMARY+=("$line")
    stop_server
}

# One viewpoint flood at rate $1 (0: as fast as the client can write).
vpflood_once() {
    local sent0 in0 vp0 inv0 sent1 in1 vp1 inv1 result how
    sent0=$(sent_total); in0=$(metric canopy_received_bytes_total); vp0=$(metric canopy_viewpoints_total)
    inv0=$(metric 'canopy_closed_total{reason="invalid"}')
    "$HOSTILE" vpflood --server "127.0.0.1:$PORT" --fingerprint "$FINGERPRINT" --rate "$1" \
        --duration "$VP_DURATION" >"$WORK/attack.log" 2>&1 &
    ATTACK=$!
    wait "$ATTACK" || true
    ATTACK=
    cat "$WORK/attack.log"
    sleep 1
    sent1=$(sent_total); in1=$(metric canopy_received_bytes_total); vp1=$(metric canopy_viewpoints_total)
    inv1=$(metric 'canopy_closed_total{reason="invalid"}')
    result=$(grep '^vpflood: ' "$WORK/attack.log" | sed 's/^vpflood: //')
    if [ "$1" = 0 ]; then how="as fast as possible"; else how="$1/s"; fi
    local line
    line=$(awk -v how="$how" -v s="$((sent1 - sent0))" -v i="$((in1 - in0))" -v v="$((vp1 - vp0))" \
        -v inv="$((inv1 - inv0))" -v r="$result" 'BEGIN {
        printf "vpflood (%s): server took %d viewpoints, received %d B, sent %d B of frames: %.1f B per byte received (%s closed as invalid); client: %s",
            how, v, i, s, s / (i > 0 ? i : 1), (inv > 0 ? "session" : "session not"), r;
    }')
    echo "$line"
    SUMMARY+=("$line")
}

scenario_vpflood() {
    start_server
    vpflood_once 0
    vpflood_once "$VP_RATE"
    stop_server
}

for s in $SCENARIOS; do
    case "$s" in
        nonack | flood | vpflood) "scenario_$s" ;;
        *) echo "hostile-run: unknown scenario $s" >&2; exit 2 ;;
    esac
done
echo "---- summary ($(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg))"
printf '%s\n' "${SUMMARY[@]}"
