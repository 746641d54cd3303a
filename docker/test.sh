#!/usr/bin/env bash
# End-to-end test of the container stack, run by CI after `make test` and `make e2e`:
#   build the image (offline; a local base image when no registry answers), bring the compose
#   stack up on a free port, wait until every container is healthy, plan and execute a motion
#   from the host, scale the planners to 2, race them, kill one planner process and plan again,
#   see the restart policy bring it back, tear everything down. Every running container's mounts
#   are checked for secrets: the plain stack mounts none.
#   Then the secured stack (compose.secure.yaml, a cell from configs/security/setup_cell.sh): it
#   refuses the example passwords, comes up with the cell's own, each container mounts only its
#   own secrets (0 of another identity's, never the CA key), the operator plans and executes,
#   and the viewer's plan is dropped.
#
#   docker/test.sh            (needs root or sudo for installing and starting the engine)
#
# Installs docker.io, docker-compose and debootstrap from Debian when missing and starts
# dockerd when no engine answers (and stops only that one at the end). Uses the host's .venv
# (`make setup`) for the host-side client.
set -euo pipefail
cd "$(dirname "$0")/.."
started=$(date +%s)

sudo=""; [ "$(id -u)" = 0 ] || sudo=sudo
python=${PYTHON:-.venv/bin/python}
image=${ROBONAV_TEST_IMAGE:-robonav-arm:test}
project=robonav-test-$$
dockerd_pid=""
workdir=$(mktemp -d /tmp/robonav-docker-test.XXXXXX)
[ -x "$python" ] || make setup  # the host-side client and the wheel builder
robonav=$(cd "$(dirname "$python")" && pwd)/robonav  # absolute: the secured clients run in their own directory

log() { echo "[docker/test.sh +$(( $(date +%s) - started ))s] $*"; }

# --- the engine -----------------------------------------------------------------------------
missing=""
command -v dockerd >/dev/null || missing="$missing docker.io"
command -v docker-compose >/dev/null || docker compose version >/dev/null 2>&1 || missing="$missing docker-compose"
command -v debootstrap >/dev/null || missing="$missing debootstrap"
if [ -n "$missing" ]; then
    log "installing Debian packages:$missing"
    $sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq $missing >/dev/null
fi
if ! docker info >/dev/null 2>&1; then
    log "starting dockerd"
    $sudo dockerd >"$workdir/dockerd.log" 2>&1 &
    dockerd_pid=$!
    for _ in $(seq 60); do docker info >/dev/null 2>&1 && break; sleep 1; done
    docker info >/dev/null 2>&1 || { tail -20 "$workdir/dockerd.log"; echo "dockerd did not start" >&2; exit 1; }
fi
if command -v docker-compose >/dev/null; then compose=(docker-compose); else compose=(docker compose); fi
compose+=(-p "$project" -f docker/compose.yaml)
secure=("${compose[@]}" -f docker/compose.secure.yaml)

cleanup() {
    local code=$?
    if [ "$code" != 0 ]; then
        log "FAILED (exit $code); container logs:"
        "${compose[@]}" ps || true
        "${compose[@]}" logs --no-color --tail 40 || true
    fi
    "${compose[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
    if [ -n "${ROBONAV_SECURITY_DIR:-}" ]; then
        "${secure[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
    fi
    if [ -n "$dockerd_pid" ]; then
        $sudo kill "$dockerd_pid" 2>/dev/null || true
        wait "$dockerd_pid" 2>/dev/null || true
    fi
    $sudo rm -rf "$workdir"  # the containers' secrets belong to their user (uid 1000) by then
    exit "$code"
}
trap cleanup EXIT

# --- image ----------------------------------------------------------------------------------
build_started=$(date +%s)
PYTHON=$python docker/build.sh "$image"
size_mb=$(docker image inspect -f '{{.Size}}' "$image" | awk '{printf "%.0f", $1 / 1e6}')
log "image $image built in $(( $(date +%s) - build_started )) s: ${size_mb} MB"

# --- config: the packaged default on a free port, the arm following setpoints exactly -------
port=$("$python" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
"$python" - "$workdir/robonav.yaml" "$port" <<'EOF'
import sys
import yaml
from robonav.services.config import default_config_path, load_config
data = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
data["zenoh"]["connect"] = [f"tcp/127.0.0.1:{sys.argv[2]}"]
data["sim"]["follow"] = "kinematic"  # results independent of how busy the machine is
# A shared 2-core machine can starve the sim and perception for seconds; this tests the
# containers, not how fresh the map stays under such load.
data["planner"]["occupancy_max_age_s"] = 60.0
with open(sys.argv[1], "w", encoding="utf-8") as out:
    yaml.safe_dump(data, out, sort_keys=False)
load_config(sys.argv[1])
EOF
chmod 755 "$workdir" && chmod 644 "$workdir/robonav.yaml"
export ROBONAV_IMAGE=$image ROBONAV_CONFIG_DIR=$workdir ROBONAV_CONFIG=robonav.yaml
export ROBONAV_ROUTER_LISTEN=tcp/127.0.0.1:$port
goals=$("$python" -c 'from robonav.services.config import load_config; import sys
for g in load_config(sys.argv[1]).demo.goals_rad: print(" ".join(map(str, g)))' "$workdir/robonav.yaml")
goal0=$(sed -n 1p <<<"$goals"); goal1=$(sed -n 2p <<<"$goals"); goal2=$(sed -n 3p <<<"$goals")

containers() { "${compose[@]}" ps -q "$@"; }

wait_healthy() {  # wait_healthy TIMEOUT_S: every container of the project healthy
    local deadline=$(( $(date +%s) + $1 )) states
    while true; do
        states=$(containers | xargs -r docker inspect -f '{{.Name}} {{if .State.Health}}{{.State.Health.Status}}{{else}}none{{end}}')
        if ! grep -qv ' healthy$' <<<"$states"; then return 0; fi
        if [ "$(date +%s)" -gt "$deadline" ]; then echo "$states" >&2; return 1; fi
        sleep 2
    done
}

plan() {  # plan ARGS...: robonav plan against the stack, output in $workdir/plan.json
    "$robonav" plan --config "$workdir/robonav.yaml" --timeout 60 --json "$workdir/plan.json" "$@" >/dev/null
}

plan_until_ok() {  # the planner refuses to plan until perception's first map reached it
    local deadline=$(( $(date +%s) + $1 )); shift
    until plan "$@"; do
        [ "$(date +%s)" -lt "$deadline" ] || { cat "$workdir/plan.json" >&2; return 1; }
        sleep 2
    done
}

field() { "$python" -c 'import json, sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])' "$workdir/plan.json" "$1"; }

is_secret() {  # is_secret PATH: a private key, a password dictionary, or a client config holding a password
    case "$(basename "$1")" in *.key|credentials.txt|client-*.json5) return 0 ;; *) return 1 ;; esac
}

check_mounts() {  # check_mounts [SECURITY_DIR]: no running container mounts a secret of another identity
    local security=${1:-} c service own own_n foreign_n type src f
    for c in $(containers); do
        service=$(docker inspect -f '{{index .Config.Labels "com.docker.compose.service"}}' "$c")
        own=${security:+$security/$service}
        own_n=0; foreign_n=0
        while read -r type src; do
            [ "$type" = bind ] || continue
            while IFS= read -r f; do
                is_secret "$f" || continue
                if [ -n "$own" ] && [[ "$f" == "$own"/* ]]; then
                    own_n=$((own_n + 1))
                else
                    foreign_n=$((foreign_n + 1))
                    echo "  $service mounts a secret it does not need: $f" >&2
                fi
            done < <($sudo find "$src" -type f)
        done < <(docker inspect -f '{{range .Mounts}}{{.Type}} {{.Source}}{{"\n"}}{{end}}' "$c")
        log "secrets mounted into $service (${c:0:12}): $own_n of its own, $foreign_n of others"
        [ "$foreign_n" = 0 ] || return 1
    done
}

# --- the stack ------------------------------------------------------------------------------
stack_started=$(date +%s)
"${compose[@]}" up -d
wait_healthy 300
log "stack healthy in $(( $(date +%s) - stack_started )) s: $(containers | wc -l) containers"
for service in router sim perception planner executor; do  # the image's health check, run by hand
    "${compose[@]}" exec -T "$service" python -m robonav.services.health
done
check_mounts  # the plain stack mounts the YAML alone: no secret at all

plan_until_ok 120 --goal $goal0 --execute
log "planned and executed from the host: $(field result), planner $(field planner_id), $(field waypoint_count) waypoints"

"${compose[@]}" up -d --no-recreate --scale planner=2
wait_healthy 300
[ "$(containers planner | wc -l)" = 2 ] || { echo "expected 2 planners" >&2; exit 1; }
plan_until_ok 60 --goal $goal1 --race --execute
log "2 planners: the race answered from $(field replier): $(field result)"

victim=$(containers planner | sed -n 1p)  # sed reads it all: `head` can end the pipe early (SIGPIPE under pipefail)
pid=$(docker inspect -f '{{.State.Pid}}' "$victim")
$sudo kill -9 "$pid"  # the planner process dies as in a crash; the container exits with it
for _ in $(seq 20); do [ "$(docker inspect -f '{{.State.Pid}}' "$victim")" != "$pid" ] && break; sleep 0.5; done
for race in "" --race; do
    plan_until_ok 60 --goal $goal2 $race
done
log "killed planner ${victim:0:12} (pid $pid); the other kept serving: replier $(field replier)"
plan_until_ok 60 --goal $goal2 --execute

wait_healthy 300
restarts=$(docker inspect -f '{{.RestartCount}}' "$victim")
[ "$restarts" -ge 1 ] || { echo "the killed planner was not restarted" >&2; exit 1; }
log "restart policy: the killed planner is back and healthy (restarts: $restarts)"

"${compose[@]}" down -v --remove-orphans

# --- the secured stack ----------------------------------------------------------------------
security=$workdir/security
configs/security/setup_cell.sh "$security" >/dev/null
example=$workdir/example-security  # the same cell, but the router accepts the example passwords
cp -r "$security" "$example"
cp configs/security/credentials.txt "$example/router/credentials.txt"
"$python" - "$workdir/robonav.yaml" "$workdir/robonav-secure.yaml" "$port" <<'EOF'
import sys
import yaml
data = yaml.safe_load(open(sys.argv[1], encoding="utf-8"))
data["zenoh"]["connect"] = [f"tls/localhost:{sys.argv[3]}"]
with open(sys.argv[2], "w", encoding="utf-8") as out:
    yaml.safe_dump(data, out, sort_keys=False)
EOF
chmod 644 "$workdir/robonav-secure.yaml"
for identity in router sim perception planner executor; do  # the image's user reads the containers' own
    $sudo chown -R 1000:1000 "$security/$identity" "$example/$identity"
done
export ROBONAV_CONFIG=robonav-secure.yaml ROBONAV_ROUTER_LISTEN=tls/127.0.0.1:$port

set +e
refusal=$(ROBONAV_SECURITY_DIR=$example ROBONAV_DEV_STACK=0 "${secure[@]}" run --rm --no-deps -T router 2>&1)
refused_code=$?
set -e
if [ "$refused_code" != 2 ] || ! grep -q "example password" <<<"$refusal"; then
    echo "$refusal" >&2
    echo "the secured router did not refuse the example passwords (exit $refused_code)" >&2
    exit 1
fi
log "secured router with the example passwords: refused (exit 2)"

export ROBONAV_SECURITY_DIR=$security
stack_started=$(date +%s)
"${secure[@]}" up -d
wait_healthy 300
log "secured stack healthy in $(( $(date +%s) - stack_started )) s: $(containers | wc -l) containers"
check_mounts "$security"
for c in $(containers); do  # nor is the CA's key anywhere inside a container
    if docker exec "$c" sh -c 'find / \( -path /proc -o -path /sys \) -prune -o -name ca.key -print 2>/dev/null' | grep -q .; then
        echo "container $c holds the CA key" >&2
        exit 1
    fi
done

secure_plan() {  # secure_plan IDENTITY ARGS...: robonav plan from the host, logged in as IDENTITY
    local identity=$1; shift
    (cd "$security/$identity" && "$robonav" plan --config "$workdir/robonav-secure.yaml" \
        --zenoh-config "client-$identity.json5" --json "$workdir/plan.json" "$@" >/dev/null)
}
deadline=$(( $(date +%s) + 120 ))
until secure_plan operator --timeout 60 --goal $goal0 --execute; do
    [ "$(date +%s)" -lt "$deadline" ] || { cat "$workdir/plan.json" >&2; exit 1; }
    sleep 2
done
log "secured: the operator planned and executed: $(field result)"
set +e
secure_plan viewer --timeout 5 --goal $goal1
viewer_code=$?
set -e
[ "$viewer_code" = 3 ] || { echo "the viewer's plan was not dropped (exit $viewer_code)" >&2; exit 1; }
log "secured: the viewer's plan got no answer (exit 3)"
"${secure[@]}" down -v --remove-orphans
log "passed: docker/test.sh wall time $(( $(date +%s) - started )) s, image $image ${size_mb} MB"
