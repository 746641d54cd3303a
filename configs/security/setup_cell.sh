#!/usr/bin/env bash
# A secured cell's secrets, one directory per identity, so that each container mounts only its own.
#
#   setup_cell.sh [--rotate-passwords] DIR
#
# DIR receives
#   ca/          the cell CA and the router certificate (gen_certs.sh). ca.key signs certificates:
#                keep it offline; no container mounts anything from ca/.
#   router/      router-acl.json5, credentials.txt (every identity's password), client-health.json5
#                (the router container's health check) and certs/{ca.pem,router.pem,router.key}
#   <identity>/  client-<identity>.json5 (its own password) and certs/ca.pem, for sim, perception,
#                planner, executor (the containers) and operator, viewer (host-side tools)
#
# Passwords are random (openssl rand) and made once: running the script again keeps them and the
# certificates, and only copies what is missing. --rotate-passwords writes new passwords for every
# identity. Certificates: delete ca/router.pem to re-issue the router's (same CA), or ca/ for a new
# CA (every identity then gets the new ca.pem). Restart the router and the services afterwards
# (docs/operations.md, "Rotating passwords and certificates"). ROUTER_HOSTS, ROUTER_IPS and DAYS are
# passed to gen_certs.sh.
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
rotate=0
if [ "${1:-}" = "--rotate-passwords" ]; then rotate=1; shift; fi
[ $# -eq 1 ] || { echo "usage: setup_cell.sh [--rotate-passwords] DIR" >&2; exit 2; }
out=$1
identities=(sim perception planner executor operator viewer health)
command -v openssl >/dev/null || { echo "setup_cell.sh: openssl is required" >&2; exit 1; }

umask 077
mkdir -p "$out/ca" "$out/router/certs"
bash "$here/gen_certs.sh" "$out/ca" none >/dev/null

# The passwords: the router's dictionary is where they live; made once unless rotated.
credentials="$out/router/credentials.txt"
declare -A password=()
if [ -f "$credentials" ] && [ "$rotate" = 0 ]; then
    while IFS=: read -r user secret; do [ -n "$user" ] && password[$user]=$secret; done < "$credentials"
fi
new_password() { openssl rand -base64 48 | tr -dc 'A-Za-z0-9' | head -c 32; }
: > "$credentials.new"
for id in "${identities[@]}"; do
    [ -n "${password[$id]:-}" ] || password[$id]=$(new_password)
    printf '%s:%s\n' "$id" "${password[$id]}" >> "$credentials.new"
done
mv "$credentials.new" "$credentials"

# client_file IDENTITY DIR: the example client config with the identity's own password.
client_file() {
    local id=$1 dir=$2
    sed "s|example-$id-password|${password[$id]}|; s|^// Example password:.*|// Written by setup_cell.sh: this identity's own password; keep this file private.|" \
        "$here/client-$id.json5" > "$dir/client-$id.json5"
    grep -q "${password[$id]}" "$dir/client-$id.json5" || { echo "setup_cell.sh: no password field in client-$id.json5" >&2; exit 1; }
}

cp "$here/router-acl.json5" "$out/router/"
cp "$out/ca/ca.pem" "$out/ca/router.pem" "$out/ca/router.key" "$out/router/certs/"
client_file health "$out/router"
for id in sim perception planner executor operator viewer; do
    mkdir -p "$out/$id/certs"
    cp "$out/ca/ca.pem" "$out/$id/certs/"
    client_file "$id" "$out/$id"
done

# Secrets readable by their owner only; certificates and the ACL are public.
chmod 700 "$out/ca"
find "$out" -mindepth 1 -maxdepth 1 -type d ! -name ca -exec chmod 755 {} + -exec chmod 755 {}/certs \;
find "$out" -type f \( -name '*.key' -o -name 'client-*.json5' -o -name credentials.txt \) -exec chmod 600 {} +
find "$out" -type f \( -name '*.pem' -o -name 'router-acl.json5' \) -exec chmod 644 {} +
echo "cell secrets in $out: router/ and ${identities[*]:0:6} (one directory each); the CA in ca/ stays offline"
[ "$rotate" = 0 ] || echo "passwords rotated: restart the router and every service, and hand operator/ and viewer/ to their users"
