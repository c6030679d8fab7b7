#!/usr/bin/env bash
# A VSM cluster on loopback: one etcd, three vsmd nodes (n1, n2, n3) sharing the data root
# DIR/data, and nginx in front with deploy/nginx/vsm.conf (README: "Running more than one node").
#
#   deploy/local-cluster.sh up DIR      start everything on free ports, wait until every node is
#                                       ready, write DIR/cluster.env
#   deploy/local-cluster.sh down DIR    stop everything `up` started in DIR
#
# DIR/cluster.env (shell syntax): FRONT=http://127.0.0.1:PORT (nginx, HTTP/1.1),
# FRONT_TLS=https://127.0.0.1:PORT (nginx, HTTP/2 with a self-signed certificate DIR/nginx/cert.pem),
# ETCD=..., N1=..., N2=..., N3=... (the nodes), and PID_N1, PID_N2, PID_N3, PID_NGINX, PID_ETCD.
# Models placed in DIR/data before `up` are served. Logs go to DIR/logs/. DIR is one local file
# system, which gives every node what a shared one must (README, "What the shared file system
# must provide"): atomic rename, durable fsync, stable inodes, and flock seen by every node.
#
# Environment: VSMD (default build/server/vsmd, built with deploy/build.sh when missing),
# VSM_MEMORY_BUDGET (per node, default 256MiB), VSM_LEASE_TTL (default 10s), VSM_TOKEN_FILE (a
# token file every node uses), VSMD_ARGS (more flags for every node), VSM_NODES (1 to 3 nodes,
# default 3; the others' lines in cluster.env are empty).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)

usage() {
  echo "usage: deploy/local-cluster.sh up|down DIR" >&2
  exit 2
}
(($# == 2)) || usage
COMMAND=$1
DIR=$(realpath -m "$2")
ENV_FILE="$DIR/cluster.env"

# Sends TERM to each pid, waits up to 15 s for them to go, then KILL.
stop_pids() {
  local pid deadline=$((SECONDS + 15))
  for pid in "$@"; do kill -TERM "$pid" 2>/dev/null || true; done
  for pid in "$@"; do
    while kill -0 "$pid" 2>/dev/null && ((SECONDS < deadline)); do sleep 0.1; done
    kill -KILL "$pid" 2>/dev/null || true
  done
}

down() {
  if [[ ! -f "$ENV_FILE" ]]; then
    echo "local-cluster: no cluster in $DIR (no cluster.env)" >&2
    exit 1
  fi
  # shellcheck disable=SC1090
  source "$ENV_FILE"
  # The front first, then the nodes (each hands its models over as it stops), etcd last.
  stop_pids "${PID_NGINX:-}"
  stop_pids "${PID_N1:-}" "${PID_N2:-}" "${PID_N3:-}"
  stop_pids "${PID_ETCD:-}"
  rm -f "$ENV_FILE"
  echo "local-cluster: stopped"
}

# What `up` needs and Debian has: etcd (etcd-server), nginx, openssl, curl.
install_missing() {
  local missing=()
  command -v etcd >/dev/null || missing+=(etcd-server)
  command -v nginx >/dev/null || [[ -x /usr/sbin/nginx ]] || missing+=(nginx-light)
  command -v openssl >/dev/null || missing+=(openssl)
  command -v curl >/dev/null || missing+=(curl)
  if ((${#missing[@]})); then
    echo "local-cluster: installing ${missing[*]}"
    local sudo=""
    [[ $(id -u) -eq 0 ]] || sudo=sudo
    $sudo apt-get update -q
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q --no-install-recommends "${missing[@]}"
  fi
}

# N free TCP ports on 127.0.0.1, one per line (bound together, so they differ).
free_ports() {
  python3 - "$1" <<'PY'
import socket, sys
sockets = []
for _ in range(int(sys.argv[1])):
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    sockets.append(s)
for s in sockets:
    print(s.getsockname()[1])
PY
}

# Waits up to $2 seconds until URL $1 answers 200.
wait_for() {
  local deadline=$((SECONDS + $2))
  until curl -sf -o /dev/null --max-time 1 "$1"; do
    if ((SECONDS >= deadline)); then
      echo "local-cluster: $1 did not answer in $2 s (logs in $DIR/logs/)" >&2
      return 1
    fi
    sleep 0.1
  done
}

up() {
  if [[ -f "$ENV_FILE" ]]; then
    echo "local-cluster: $DIR already has a cluster (deploy/local-cluster.sh down $DIR)" >&2
    exit 1
  fi
  install_missing
  local vsmd=${VSMD:-$ROOT/build/server/vsmd}
  if [[ ! -x "$vsmd" ]]; then
    "$ROOT/deploy/build.sh"
  fi
  local nginx
  nginx=$(command -v nginx || echo /usr/sbin/nginx)
  mkdir -p "$DIR/data" "$DIR/logs" "$DIR/etcd" "$DIR/nginx/cache" "$DIR/nginx/temp"
  local ports
  mapfile -t ports < <(free_ports 7)
  local etcd_port=${ports[0]} peer_port=${ports[1]} front_port=${ports[5]} tls_port=${ports[6]}
  local etcd_url="http://127.0.0.1:$etcd_port"
  local -A pid url

  # Started in sessions of their own, so they outlive this script and its terminal.
  setsid etcd --name local --data-dir "$DIR/etcd/data" \
    --listen-client-urls "$etcd_url" --advertise-client-urls "$etcd_url" \
    --listen-peer-urls "http://127.0.0.1:$peer_port" \
    --initial-advertise-peer-urls "http://127.0.0.1:$peer_port" \
    --initial-cluster "local=http://127.0.0.1:$peer_port" \
    >"$DIR/logs/etcd.log" 2>&1 </dev/null &
  pid[ETCD]=$!
  # Written at once, so that `down` can stop what started even when a later step fails.
  write_env() {
    {
      echo "FRONT=http://127.0.0.1:$front_port"
      echo "FRONT_TLS=https://127.0.0.1:$tls_port"
      echo "ETCD=$etcd_url"
      for n in N1 N2 N3; do echo "$n=${url[$n]:-}"; done
      for p in N1 N2 N3 NGINX ETCD; do echo "PID_$p=${pid[$p]:-}"; done
    } >"$ENV_FILE.tmp"
    mv "$ENV_FILE.tmp" "$ENV_FILE"
  }
  write_env
  wait_for "$etcd_url/health" 30

  local count=${VSM_NODES:-3}
  if ! [[ "$count" =~ ^[123]$ ]]; then
    echo "local-cluster: VSM_NODES must be 1, 2 or 3 (got '$count')" >&2
    exit 2
  fi
  local token_args=()
  [[ -n "${VSM_TOKEN_FILE:-}" ]] && token_args=(--token-file "$VSM_TOKEN_FILE")
  local i
  for ((i = 1; i <= count; i++)); do
    local port=${ports[$((i + 1))]}
    url[N$i]="http://127.0.0.1:$port"
    # The nginx front is one client to every node: event streams are bounded per node only.
    # shellcheck disable=SC2086
    setsid "$vsmd" --listen "127.0.0.1:$port" --data-root "$DIR/data" \
      --coordinator "$etcd_url" --node "n$i" --advertise "${url[N$i]}" \
      --memory-budget "${VSM_MEMORY_BUDGET:-256MiB}" \
      --set "cluster.lease_ttl=${VSM_LEASE_TTL:-10s}" \
      --set limits.event_subscribers_per_client=64 "${token_args[@]}" ${VSMD_ARGS:-} \
      >"$DIR/logs/n$i.log" 2>&1 </dev/null &
    pid[N$i]=$!
  done
  write_env

  openssl req -x509 -newkey rsa:2048 -nodes -days 365 -subj "/CN=localhost" \
    -addext "subjectAltName=IP:127.0.0.1,DNS:localhost" \
    -keyout "$DIR/nginx/key.pem" -out "$DIR/nginx/cert.pem" 2>/dev/null
  {
    echo "upstream vsm_nodes {"
    echo "    hash \$vsm_shard consistent;"
    for ((i = 1; i <= count; i++)); do
      echo "    server ${url[N$i]#http://} max_fails=1 fail_timeout=5s;"
    done
    echo "    keepalive 32;"
    echo "}"
  } >"$DIR/nginx/nodes.conf"
  sed -e "s|listen 8080;|listen 127.0.0.1:$front_port;|" \
    -e "s|listen 8443 ssl http2;|listen 127.0.0.1:$tls_port ssl http2;|" \
    -e "s|/etc/nginx/vsm/|$DIR/nginx/|g" \
    -e "s|/var/cache/nginx/vsm|$DIR/nginx/cache|" \
    "$ROOT/deploy/nginx/vsm.conf" >"$DIR/nginx/vsm.conf"
  cat >"$DIR/nginx/nginx.conf" <<CONF
# Written by deploy/local-cluster.sh.
daemon off;
pid $DIR/nginx/nginx.pid;
error_log $DIR/logs/nginx-error.log warn;
worker_processes 1;
events { worker_connections 1024; }
http {
    access_log $DIR/logs/nginx-access.log;
    client_body_temp_path $DIR/nginx/temp/body;
    proxy_temp_path $DIR/nginx/temp/proxy;
    fastcgi_temp_path $DIR/nginx/temp/fastcgi;
    uwsgi_temp_path $DIR/nginx/temp/uwsgi;
    scgi_temp_path $DIR/nginx/temp/scgi;
    include $DIR/nginx/nodes.conf;
    include $DIR/nginx/vsm.conf;
}
CONF
  "$nginx" -t -q -c "$DIR/nginx/nginx.conf"
  setsid "$nginx" -c "$DIR/nginx/nginx.conf" >"$DIR/logs/nginx.log" 2>&1 </dev/null &
  pid[NGINX]=$!
  write_env

  for ((i = 1; i <= count; i++)); do wait_for "${url[N$i]}/readyz" 60; done
  wait_for "http://127.0.0.1:$front_port/readyz" 30
  echo "local-cluster: up; front http://127.0.0.1:$front_port and https://127.0.0.1:$tls_port," \
    "nodes ${url[*]}, etcd $etcd_url ($ENV_FILE)"
}

case "$COMMAND" in
  up) up ;;
  down) down ;;
  *) usage ;;
esac
