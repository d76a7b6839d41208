#!/usr/bin/env bash
# Make a fleet CA and TLS certificates for the base station and each robot.
#
#   deploy/make_certs.sh OUTDIR ROBOT_ID [ROBOT_ID ...]
#
# Writes into OUTDIR (created if needed, private keys mode 600):
#   ca.pem, ca.key                   the fleet CA (reused if it is already there, as
#                                    are existing certificates: robots can be added later)
#   basestation.pem, basestation.key CN=basestation, SAN = $BASE_HOSTS
#   <id>.pem, <id>.key               CN=<id> (the access-control subject), one per robot
#
# Environment:
#   BASE_HOSTS  comma list of names/IPs the robots use to reach the base station
#               (checked against the certificate on connect), e.g.
#               BASE_HOSTS=basestation.local,192.168.8.1; localhost and 127.0.0.1 are
#               always added (the base station behind a zenohd router on the laptop)
#   CA_NAME     CA common name (default "collabslam fleet CA")
#   DAYS        validity in days (default 825)
#   OPENSSL     openssl binary (default: openssl on PATH)
#   FORCE       if set, remake certificates that already exist (default: keep them)
#
# Keys are ECDSA P-256 in PKCS#8 PEM (what Zenoh's rustls TLS link reads). The
# output is secret: never commit it (deploy/.gitignore ignores certs/ and *.key).
set -euo pipefail

usage() { echo "usage: $0 OUTDIR ROBOT_ID [ROBOT_ID ...]" >&2; exit 2; }
[[ $# -ge 2 ]] || usage
OUT=$1; shift
OPENSSL=${OPENSSL:-openssl}
DAYS=${DAYS:-825}
CA_NAME=${CA_NAME:-collabslam fleet CA}
BASE_HOSTS_GIVEN=${BASE_HOSTS:-}
BASE_HOSTS=${BASE_HOSTS:+$BASE_HOSTS,}localhost,127.0.0.1

valid_id='^[A-Za-z0-9_-]{1,32}$'   # same rule as protocol/keys.py
for id in "$@"; do
  [[ $id =~ $valid_id ]] || { echo "invalid robot id '$id' (1-32 of A-Z a-z 0-9 _ -)" >&2; exit 2; }
  [[ $id != basestation && $id != ca ]] || { echo "robot id '$id' is reserved" >&2; exit 2; }
done

mkdir -p "$OUT"
umask 077
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

newkey() { "$OPENSSL" genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

san_list() {  # "a,1.2.3.4" -> "DNS:a,IP:1.2.3.4" (duplicates dropped)
  local out=() h
  local -A seen=()
  IFS=',' read -ra hosts <<< "$1"
  for h in "${hosts[@]}"; do
    [[ -n $h && -z ${seen[$h]:-} ]] || continue
    seen[$h]=1
    if [[ $h =~ ^[0-9.]+$ || $h == *:* ]]; then out+=("IP:$h"); else out+=("DNS:$h"); fi
  done
  (IFS=','; echo "${out[*]}")
}

if [[ -f $OUT/ca.pem && ! -f $OUT/ca.key ]]; then
  # a new CA would replace ca.pem, and no certificate signed before would verify
  echo "$OUT/ca.key is missing (kept offline?): put it back beside ca.pem to sign new" \
    "certificates; no new CA is made" >&2
  exit 1
fi
if [[ ! -f $OUT/ca.key || ! -f $OUT/ca.pem ]]; then
  newkey "$OUT/ca.key"
  "$OPENSSL" req -x509 -new -key "$OUT/ca.key" -sha256 -days "$DAYS" -subj "/CN=$CA_NAME" \
    -addext "basicConstraints=critical,CA:TRUE,pathlen:0" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -out "$OUT/ca.pem"
  echo "made CA $OUT/ca.pem"
fi

sans_of() {  # the names in a certificate, as san_list writes them
  "$OPENSSL" x509 -in "$1" -noout -ext subjectAltName 2>/dev/null | tail -n 1 |
    sed -e 's/IP Address:/IP:/g' -e 's/, /,/g' -e 's/^ *//'
}

# leaf NAME SAN: a certificate signed by the CA, usable as TLS server and client. One
# already there is kept (FORCE=1 remakes it), except the base station's when BASE_HOSTS
# is given and names other hosts than it has (the robots' certificates stay good: the
# CA is the same). Run without BASE_HOSTS (adding a robot; sudo drops the variable),
# the base station's is kept whatever its names: the names are printed either way.
leaf() {
  local name=$1 san=$2 has
  if [[ -f $OUT/$name.pem && -f $OUT/$name.key && -z ${FORCE:-} ]]; then
    has=$(sans_of "$OUT/$name.pem")
    if [[ $name != basestation || -z $BASE_HOSTS_GIVEN || $has == "$san" ]]; then
      echo "kept $OUT/$name.pem (${has:-names unknown}; FORCE=1 to remake it)"; return
    fi
    echo "remaking $OUT/$name.pem: its names $has are not BASE_HOSTS' $san"
  fi
  newkey "$OUT/$name.key"
  "$OPENSSL" req -new -key "$OUT/$name.key" -subj "/CN=$name" -out "$tmp/$name.csr"
  cat > "$tmp/$name.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$san
EOF
  "$OPENSSL" x509 -req -in "$tmp/$name.csr" -CA "$OUT/ca.pem" -CAkey "$OUT/ca.key" \
    -CAcreateserial -CAserial "$tmp/ca.srl" -days "$DAYS" -sha256 \
    -extfile "$tmp/$name.ext" -out "$OUT/$name.pem" 2>/dev/null
  echo "made $OUT/$name.pem (CN=$name, $san)"
}

leaf basestation "$(san_list "$BASE_HOSTS")"
for id in "$@"; do
  leaf "$id" "DNS:$id"
done
chmod 644 "$OUT"/*.pem
