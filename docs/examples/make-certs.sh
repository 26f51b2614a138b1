#!/usr/bin/env bash
# A private certificate authority and one certificate per Zenoh node, for docs/deployment.md.
#
#   bash docs/examples/make-certs.sh DIR [HOST ...]
#
# DIR gets ca.pem (the authority's certificate: give it to every node), ca.key (keep it offline),
# and for each node NAME: NAME.pem + NAME.key. The common name (CN) of a node's certificate is its
# NAME: the router's access-control rules match on it (`cert_common_names`). The router's
# certificate is valid for the HOSTs given (names or IP addresses; default localhost 127.0.0.1).
# Nodes: router, server (the mapper/log host), robot1, robot2, viewer. Run it again with other names by
# setting NODES="robot2 robot3".
set -euo pipefail
dir=${1:?usage: make-certs.sh DIR [HOST ...]}
shift
hosts=("$@")
[ ${#hosts[@]} -gt 0 ] || hosts=(localhost 127.0.0.1)
nodes=${NODES:-server robot1 robot2 viewer}
days=${DAYS:-825}
mkdir -p "$dir"
cd "$dir"
key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

if [ ! -f ca.pem ]; then
  key ca.key
  openssl req -x509 -new -key ca.key -sha256 -days "$days" -subj "/CN=octolog-ca" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" -out ca.pem
fi

sign() {  # NAME EXTFILE
  key "$1.key"
  openssl req -new -key "$1.key" -subj "/CN=$1" -out "$1.csr"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -sha256 -days "$days" \
    -extfile "$2" -out "$1.pem" 2>/dev/null
  rm -f "$1.csr" "$2"
}

san=""
for h in "${hosts[@]}"; do
  if [[ $h =~ ^[0-9.]+$ || $h == *:* ]]; then san+="IP:$h,"; else san+="DNS:$h,"; fi
done
printf 'basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=%s\n' \
  "${san%,}" > router.ext
sign router router.ext
for n in $nodes; do
  printf 'basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=clientAuth\n' > "$n.ext"
  sign "$n" "$n.ext"
done
chmod 600 ./*.key
echo "certificates in $dir: ca.pem, router.pem, $(for n in $nodes; do printf '%s.pem ' "$n"; done)"
