#!/usr/bin/env bash
# A Canopy cluster on loopback: a 3-node NATS JetStream cluster (Debian's nats-server), then N canopy-server edges
# that keep their edits in it (`--edits nats://…`) and share one certificate. Everything listens on 127.0.0.1 only.
#
#   scripts/cluster.sh up [EDGES]      # start (EDGES edges, default 0: the NATS cluster alone); prints the addresses
#   scripts/cluster.sh status          # what runs
#   scripts/cluster.sh kill nats I     # SIGKILL NATS node I (0..2)
#   scripts/cluster.sh kill edge J     # SIGKILL edge J
#   scripts/cluster.sh start nats I    # start NATS node I again (same store directory)
#   scripts/cluster.sh leader          # the NATS node (0..2) leading the edit stream, as a live node reports it
#   scripts/cluster.sh down            # stop everything and remove the cluster's directory
#
# Environment: CLUSTER_DIR (default: $TMPDIR/canopy-cluster), NATS_PORT (client ports NATS_PORT..+2, routes +100..,
# monitoring +200..; default 14222), EDGE_PORT (edges' QUIC ports EDGE_PORT.., metrics +1000..; default 14433),
# CANOPY_SERVER (the binary; default target/release/canopy-server, built if missing), WORLD (a manifest for the
# edges), EDITORS (an editors file for the edges), READY_S (how long to wait for each process, default 30).
set -euo pipefail
cd "$(dirname "$0")/.."

DIR=${CLUSTER_DIR:-${TMPDIR:-/tmp}/canopy-cluster}
NATS_PORT=${NATS_PORT:-14222}
EDGE_PORT=${EDGE_PORT:-14433}
READY_S=${READY_S:-30}
SERVER=${CANOPY_SERVER:-target/release/canopy-server}

say() { echo "cluster: $*" >&2; }

nats_urls() {
    local urls=()
    for i in 0 1 2; do urls+=("nats://127.0.0.1:$((NATS_PORT + i))"); done
    (IFS=,; echo "${urls[*]}")
}

alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

# Wait until FILE contains PATTERN or the process of PIDFILE died or READY_S passed.
wait_for() {
    local file=$1 pattern=$2 pidfile=$3 waited=0
    while ! grep -q "$pattern" "$file" 2>/dev/null; do
        if ! alive "$pidfile"; then
            say "$(basename "$pidfile" .pid) exited; its log:"
            tail -20 "$file" >&2 || true
            return 1
        fi
        if [ "$waited" -ge $((READY_S * 10)) ]; then
            say "$(basename "$pidfile" .pid) not ready within ${READY_S}s; its log:"
            tail -20 "$file" >&2 || true
            return 1
        fi
        sleep 0.1
        waited=$((waited + 1))
    done
}

start_nats() {
    local i=$1 routes=()
    command -v nats-server >/dev/null || { say "nats-server is not installed (apt-get install nats-server)"; exit 1; }
    for j in 0 1 2; do routes+=("nats-route://127.0.0.1:$((NATS_PORT + 100 + j))"); done
    mkdir -p "$DIR/js-$i"
    cat >"$DIR/nats-$i.conf" <<EOF
server_name: n$i
listen: 127.0.0.1:$((NATS_PORT + i))
http: 127.0.0.1:$((NATS_PORT + 200 + i))
jetstream {
  store_dir: "$DIR/js-$i"
  max_memory_store: 256MB
  max_file_store: 2GB
}
cluster {
  name: canopy
  listen: 127.0.0.1:$((NATS_PORT + 100 + i))
  routes: [$(IFS=,; echo "${routes[*]}")]
}
EOF
    : >"$DIR/nats-$i.log"
    nats-server -c "$DIR/nats-$i.conf" >>"$DIR/nats-$i.log" 2>&1 &
    echo $! >"$DIR/nats-$i.pid"
}

start_edge() {
    local j=$1 args=()
    [ -n "${WORLD:-}" ] && args+=(--world "$WORLD")
    [ -n "${EDITORS:-}" ] && args+=(--editors "$EDITORS")
    "$SERVER" --edits "$(nats_urls)" --listen "127.0.0.1:$((EDGE_PORT + j))" \
        --metrics "127.0.0.1:$((EDGE_PORT + 1000 + j))" --data "$DIR/edges" --stats-every 0 "${args[@]}" \
        >"$DIR/edge-$j.log" 2>&1 &
    echo $! >"$DIR/edge-$j.pid"
}

up() {
    local edges=${1:-0}
    if [ -f "$DIR/.canopy-cluster" ] && { alive "$DIR/nats-0.pid" || alive "$DIR/nats-1.pid" || alive "$DIR/nats-2.pid"; }; then
        say "already up in $DIR (scripts/cluster.sh down first)"
        exit 1
    fi
    mkdir -p "$DIR"
    touch "$DIR/.canopy-cluster"
    for i in 0 1 2; do start_nats "$i"; done
    for i in 0 1 2; do wait_for "$DIR/nats-$i.log" "Server is ready" "$DIR/nats-$i.pid"; done
    # JetStream answers once the nodes found each other and elected a meta leader.
    local waited=0
    until grep -q "JetStream cluster new metadata leader\|Self is new JetStream cluster metadata leader" "$DIR"/nats-*.log; do
        [ "$waited" -ge $((READY_S * 10)) ] && { say "no JetStream meta leader within ${READY_S}s"; exit 1; }
        sleep 0.1
        waited=$((waited + 1))
    done
    say "NATS JetStream cluster up: $(nats_urls)"
    if [ "$edges" -gt 0 ]; then
        [ -x "$SERVER" ] || cargo build --release -q -p canopy-server-app
        # The first edge makes the certificate every edge then shares (one fingerprint for clients to pin).
        for ((j = 0; j < edges; j++)); do
            start_edge "$j"
            wait_for "$DIR/edge-$j.log" "listening on" "$DIR/edge-$j.pid"
            say "edge $j: 127.0.0.1:$((EDGE_PORT + j)), metrics http://127.0.0.1:$((EDGE_PORT + 1000 + j))/metrics"
        done
        say "fingerprint $(grep -m1 '^fingerprint' "$DIR/edge-0.log" | cut -d' ' -f2)"
    fi
    echo "$(nats_urls)"
}

status() {
    [ -f "$DIR/.canopy-cluster" ] || { say "no cluster in $DIR"; exit 1; }
    for f in "$DIR"/nats-*.pid "$DIR"/edge-*.pid; do
        [ -f "$f" ] || continue
        if alive "$f"; then echo "$(basename "$f" .pid) up (pid $(cat "$f"))"; else echo "$(basename "$f" .pid) down"; fi
    done
}

# The index of the node leading the edit stream (its Raft group's leader), asked of each live node's monitoring
# endpoint (bash's /dev/tcp: no curl needed) until one names it.
leader() {
    local i json name
    for i in 0 1 2; do
        alive "$DIR/nats-$i.pid" || continue
        json=$( (exec 3<>"/dev/tcp/127.0.0.1/$((NATS_PORT + 200 + i))" &&
            printf 'GET /jsz?streams=true HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n' >&3 && cat <&3) 2>/dev/null || true)
        # The first "leader" after the stream details is the stream's (the meta leader comes before them).
        name=$(printf '%s' "$json" | sed -n '/"stream_detail"/,$p' | grep -m1 '"leader"' | sed 's/.*"leader": *"n\([0-9]\)".*/\1/')
        if [ -n "$name" ]; then
            echo "$name"
            return 0
        fi
    done
    say "no live node names the edit stream's leader"
    return 1
}

down() {
    [ -f "$DIR/.canopy-cluster" ] || { say "no cluster in $DIR"; return 0; }
    for f in "$DIR"/edge-*.pid "$DIR"/nats-*.pid; do
        [ -f "$f" ] && kill "$(cat "$f")" 2>/dev/null || true
    done
    sleep 0.5
    for f in "$DIR"/edge-*.pid "$DIR"/nats-*.pid; do
        [ -f "$f" ] && kill -9 "$(cat "$f")" 2>/dev/null || true
    done
    rm -rf "$DIR"
    say "down"
}

case "${1:-}" in
    up) up "${2:-0}" ;;
    status) status ;;
    leader) leader ;;
    down) down ;;
    kill)
        f="$DIR/${2:?nats or edge}-${3:?which}.pid"
        alive "$f" || { say "$2 $3 is not running"; exit 1; }
        kill -9 "$(cat "$f")"
        say "killed $2 $3 (SIGKILL)"
        ;;
    start)
        case "${2:-}" in
            nats) start_nats "${3:?which}"; wait_for "$DIR/nats-$3.log" "Server is ready" "$DIR/nats-$3.pid" ;;
            edge) start_edge "${3:?which}"; wait_for "$DIR/edge-$3.log" "listening on" "$DIR/edge-$3.pid" ;;
            *) say "start nats I | start edge J"; exit 2 ;;
        esac
        ;;
    *)
        sed -n '2,16p' "$0" | sed 's/^# \{0,1\}//'
        exit 2
        ;;
esac
