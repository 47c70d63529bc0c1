#!/usr/bin/env bash
# A development certificate authority and one certificate per semmap identity, for the secure profile
# (docs/SECURITY.md): mutual TLS between every service and the Zenoh router, the certificate's common name being
# the identity the router's access-control list knows. For development and tests: keys are unencrypted and the
# CA's key sits beside them. A production deployment uses its own PKI.
#
#   scripts/make-dev-certs.sh DIR [HOST...]
#
# DIR gets ca.pem (the CA every side trusts), ca.key, and <identity>.pem / <identity>.key for: router,
# orchestrator, player, odometry, detector, tracker, associator, backend, viz, slam (an external SLAM), query (a
# read-only map user). Every certificate names localhost and 127.0.0.1, plus each HOST given (a DNS name or an
# IP address: where the router runs, e.g. a compose service name "zenoh"). SEMMAP_CERT_EXTRA="a b" adds more
# identities. Existing files are kept (a second run adds only what is missing); delete DIR to start over.
set -euo pipefail

out=${1:?usage: make-dev-certs.sh DIR [HOST...]}
shift
identities="router orchestrator player odometry detector tracker associator backend viz slam query ${SEMMAP_CERT_EXTRA:-}"
days=${SEMMAP_CERT_DAYS:-365}
command -v openssl >/dev/null || { echo "error: openssl is not installed (apt-get install openssl)" >&2; exit 2; }
mkdir -p "$out"
umask 077

san="DNS:localhost,IP:127.0.0.1"
for host in "$@"; do
  if [[ $host =~ ^[0-9.]+$ || $host == *:* ]]; then san="$san,IP:$host"; else san="$san,DNS:$host"; fi
done

if [[ ! -f $out/ca.pem ]]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -sha256 -days "$days" \
    -keyout "$out/ca.key" -out "$out/ca.pem" -subj "/CN=semmap development CA" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
fi

for id in $identities; do
  [[ -f $out/$id.pem ]] && continue
  ext=$(mktemp)
  printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature,keyEncipherment\n%s\n%s\n' \
    "extendedKeyUsage=serverAuth,clientAuth" "subjectAltName=$san,DNS:$id" >"$ext"
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -sha256 -keyout "$out/$id.key" \
    -out "$out/$id.csr" -subj "/CN=$id" 2>/dev/null
  openssl x509 -req -in "$out/$id.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial -sha256 \
    -days "$days" -out "$out/$id.pem" -extfile "$ext" 2>/dev/null
  rm -f "$out/$id.csr" "$ext"
done
rm -f "$out/ca.srl"
chmod 644 "$out"/*.pem
echo "certificates for: $identities -> $out (CA: $out/ca.pem)"
