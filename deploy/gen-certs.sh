#!/usr/bin/env bash
# Development certificates for the TLS/mTLS router configuration (deploy/zenoh/router-secure.json5).
#
#   deploy/gen-certs.sh [-o OUT_DIR] [-f] [-r] [ROBOT_ID ...]
#
# Writes into OUT_DIR (default: deploy/certs, which is gitignored):
#   ca.pem / ca.key                     a private CA (keep ca.key off the fleet)
#   router.pem / router.key             the zenoh router, CN=zenoh-router, SANs below
#   service.pem / service.key           rlutf service instances, CN=rlutf-service
#   operator.pem / operator.key         operators and tools, CN=rlutf-operator
#   robot-ID.pem / robot-ID.key         one per robot, CN=robot-ID (default robots: r1 r2 r3)
#
# The ACL in router-secure.json5 (made by deploy/gen-acl.py) names these common names.
# Router SANs: DNS:zenoh-router, DNS:localhost, IP:127.0.0.1, IP:::1, plus $ROUTER_SANS
# (comma-separated openssl SAN entries, e.g. ROUTER_SANS="DNS:zenoh.example.com,IP:10.0.0.5").
# Keys are EC P-256 in PKCS#8 PEM. Development only: no passphrases, 825-day validity.
# Existing files are kept; -f regenerates everything.
# Keys are readable by their owner only (0600, directory 0700); -r makes the directory and the
# keys world-readable (0755/0644) so containers running as another uid can read a bind mount
# (the docker compose development setup). Never use -r for real keys.
set -euo pipefail

out="$(dirname "$0")/certs"
force=0
readable=0
while getopts "o:frh" opt; do
  case "$opt" in
    o) out="$OPTARG" ;;
    f) force=1 ;;
    r) readable=1 ;;
    h) sed -n '2,21p' "$0"; exit 0 ;;
    *) exit 2 ;;
  esac
done
shift $((OPTIND - 1))
robots=("$@")
[ ${#robots[@]} -eq 0 ] && robots=(r1 r2 r3)

command -v openssl >/dev/null || { echo "gen-certs.sh: openssl not found" >&2; exit 1; }
for id in "${robots[@]}"; do
  [[ "$id" =~ ^[A-Za-z0-9_-]{1,64}$ ]] || { echo "gen-certs.sh: bad robot id '$id'" >&2; exit 2; }
done

mkdir -p "$out"
if [ "$readable" = 1 ]; then dir_mode=755 key_mode=644; else dir_mode=700 key_mode=600; fi
chmod "$dir_mode" "$out"
days=825
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

newkey() { # $1: key path
  (umask 077 && openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null)
}

if [ "$force" = 1 ] || [ ! -f "$out/ca.pem" ] || [ ! -f "$out/ca.key" ]; then
  newkey "$out/ca.key"
  openssl req -x509 -new -key "$out/ca.key" -sha256 -days "$days" -subj "/O=rlutf/CN=rlutf-dev-ca" \
    -addext "basicConstraints=critical,CA:TRUE,pathlen:0" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -out "$out/ca.pem"
  force=1 # a new CA invalidates every leaf
fi

leaf() { # $1: file stem, $2: common name, $3: extendedKeyUsage, $4: subjectAltName
  local stem="$1" cn="$2" eku="$3" san="$4"
  if [ "$force" = 0 ] && [ -f "$out/$stem.pem" ] && [ -f "$out/$stem.key" ]; then
    return
  fi
  newkey "$out/$stem.key"
  openssl req -new -key "$out/$stem.key" -subj "/O=rlutf/CN=$cn" -out "$tmp/$stem.csr"
  {
    echo "basicConstraints=critical,CA:FALSE"
    echo "keyUsage=critical,digitalSignature"
    echo "extendedKeyUsage=$eku"
    echo "subjectAltName=$san"
  } >"$tmp/$stem.ext"
  openssl x509 -req -in "$tmp/$stem.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
    -CAserial "$tmp/ca.srl" -sha256 -days "$days" -extfile "$tmp/$stem.ext" -out "$out/$stem.pem" 2>/dev/null
  echo "wrote $out/$stem.pem (CN=$cn)"
}

router_san="DNS:zenoh-router,DNS:localhost,IP:127.0.0.1,IP:::1"
[ -n "${ROUTER_SANS:-}" ] && router_san="$router_san,$ROUTER_SANS"
leaf router zenoh-router "serverAuth,clientAuth" "$router_san"
leaf service rlutf-service clientAuth "DNS:rlutf-service"
leaf operator rlutf-operator clientAuth "DNS:rlutf-operator"
for id in "${robots[@]}"; do
  leaf "robot-$id" "robot-$id" clientAuth "DNS:robot-$id"
done

# Apply the requested key mode to every key (also to keys kept from an earlier run); the CA key
# stays private either way.
for key in "$out"/*.key; do
  chmod "$key_mode" "$key"
done
chmod 600 "$out/ca.key"
