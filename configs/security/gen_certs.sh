#!/usr/bin/env bash
# Generate a private certificate authority, a router certificate and client certificates for
# Zenoh TLS and mutual TLS, with openssl.
#
#   gen_certs.sh [OUT_DIR] [CLIENT_NAME ...]
#
# OUT_DIR (default: ./certs) receives ca.pem/ca.key, router.pem/router.key and one
# <name>.pem/<name>.key per client. The router certificate is valid for the names in
# ROUTER_HOSTS (comma separated, default "localhost,router") and the addresses in ROUTER_IPS
# (default "127.0.0.1"); clients check it against the host they connect to. A client
# certificate carries its name as the common name (CN), which access-control rules can match
# (`cert_common_names`). Default clients: the four services plus an operator and a viewer; the one
# name `none` makes no client certificate (passwords over server-side TLS need none).
# Existing files are kept: delete OUT_DIR to start over. Validity: DAYS (default 365).
set -euo pipefail

out=${1:-certs}
shift || true
clients=("$@")
[ ${#clients[@]} -gt 0 ] || clients=(sim perception planner executor operator viewer)
[ "${clients[*]}" != none ] || clients=()
router_hosts=${ROUTER_HOSTS:-localhost,router}
router_ips=${ROUTER_IPS:-127.0.0.1}
days=${DAYS:-365}

command -v openssl >/dev/null || { echo "gen_certs.sh: openssl is required" >&2; exit 1; }
mkdir -p "$out"
umask 077

new_key() { [ -f "$1" ] || openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

if [ ! -f "$out/ca.pem" ]; then
    new_key "$out/ca.key"
    openssl req -x509 -new -key "$out/ca.key" -sha256 -days "$days" -subj "/CN=robonav cell CA" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$out/ca.pem"
fi

# sign NAME EXTENSIONS: a leaf certificate for NAME signed by the CA.
sign() {
    local name=$1 ext=$2
    [ -f "$out/$name.pem" ] && return 0
    new_key "$out/$name.key"
    openssl req -new -key "$out/$name.key" -subj "/CN=$name" -out "$out/$name.csr"
    printf '%s\n' "$ext" > "$out/$name.ext"
    openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
        -sha256 -days "$days" -extfile "$out/$name.ext" -out "$out/$name.pem" 2>/dev/null
    rm -f "$out/$name.csr" "$out/$name.ext"
}

san=""
IFS=, read -ra hosts <<< "$router_hosts"
for h in "${hosts[@]}"; do san="$san,DNS:$h"; done
IFS=, read -ra ips <<< "$router_ips"
for ip in "${ips[@]}"; do san="$san,IP:$ip"; done
sign router "basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=${san#,}"

for name in "${clients[@]+"${clients[@]}"}"; do
    sign "$name" "basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth
subjectAltName=DNS:$name"
done

rm -f "$out/ca.srl"
# Keys stay private to their owner; certificates (and the CA certificate) are public.
chmod 600 "$out"/*.key
chmod 644 "$out"/*.pem
echo "certificates in $out: ca.pem, router.pem${clients[*]+ ${clients[*]/%/.pem}}"
