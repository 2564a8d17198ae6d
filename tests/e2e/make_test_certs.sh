#!/usr/bin/env bash
# Certificates for the Modbus/TCP Security tests, made fresh in DIR with the openssl CLI (the
# same commands docs/SECURITY.md shows for a plant):
#   ca.crt/key          the plant CA
#   server.crt/key      the gateway (CN=localhost, SAN localhost and 127.0.0.1)
#   read.crt/key        CN=hmi-1, role extension "read"
#   operate.crt/key     CN=plc-1, role extension "operate"
#   engineer.crt/key    CN=laptop-eng, role extension "engineer"
#   mapped.crt/key      CN=hmi-2, no extension, SAN DNS:hmi-2.plant (mapped by modbus_tcp.tls.roles)
#   norole.crt/key      CN=stranger, no extension, not mapped
#   foreign.crt/key     CN=plc-9, role "operate", from another CA (other-ca.crt)
#   expired.crt/key     CN=plc-old, role "operate", valid only in January 2020
#   ca2.crt, server2.*  a second CA and server certificate (reload tests)
#   other-scheme.crt/key CN=plc-3, role extension "Operator" (another scheme's name; mapped by CN)
#   named-role.crt/key  CN=laptop-2, role extension "Engineer" (mapped by modbus_tcp.tls.role_names)
#   critical.crt/key    CN=plc-4, role extension "operate" marked critical
#   critical-other.crt/key CN=plc-5, role "operate" and another critical extension nobody handles
set -euo pipefail
dir=${1:?usage: make_test_certs.sh DIR}
mkdir -p "$dir"
cd "$dir"

role_oid=1.3.6.1.4.1.50316.802.1

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1.key" 2>/dev/null; }

ca() {  # name CN
  key "$1"
  openssl req -x509 -new -key "$1.key" -out "$1.crt" -days 3650 -subj "/O=Test Plant/CN=$2" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
}

# leaf NAME CN CA EXTENSIONS...: a certificate for NAME signed by CA, valid for a year.
leaf() {
  local name=$1 cn=$2 issuer=$3
  shift 3
  key "$name"
  printf '%s\n' "basicConstraints=CA:FALSE" "$@" > "$name.ext"
  openssl req -new -key "$name.key" -out "$name.csr" -subj "/O=Test Plant/CN=$cn" 2>/dev/null
  openssl x509 -req -in "$name.csr" -CA "$issuer.crt" -CAkey "$issuer.key" -CAcreateserial -days 365 \
    -extfile "$name.ext" -out "$name.crt" 2>/dev/null
}

ca ca "Test Plant CA"
ca other-ca "Somebody Else's CA"
ca ca2 "Test Plant CA 2"

leaf server localhost ca "extendedKeyUsage=serverAuth" "subjectAltName=DNS:localhost,IP:127.0.0.1"
leaf server2 localhost ca2 "extendedKeyUsage=serverAuth" "subjectAltName=DNS:localhost,IP:127.0.0.1"
for role in read operate engineer; do
  cn=$([ $role = read ] && echo hmi-1 || { [ $role = operate ] && echo plc-1 || echo laptop-eng; })
  leaf "$role" "$cn" ca "extendedKeyUsage=clientAuth" "$role_oid=ASN1:UTF8String:$role"
done
leaf mapped hmi-2 ca "extendedKeyUsage=clientAuth" "subjectAltName=DNS:hmi-2.plant"
leaf norole stranger ca "extendedKeyUsage=clientAuth"
leaf foreign plc-9 other-ca "extendedKeyUsage=clientAuth" "$role_oid=ASN1:UTF8String:operate"
leaf ca2-operate plc-2 ca2 "extendedKeyUsage=clientAuth" "$role_oid=ASN1:UTF8String:operate"
leaf other-scheme plc-3 ca "extendedKeyUsage=clientAuth" "$role_oid=ASN1:UTF8String:Operator"
leaf named-role laptop-2 ca "extendedKeyUsage=clientAuth" "$role_oid=ASN1:UTF8String:Engineer"
leaf critical plc-4 ca "extendedKeyUsage=clientAuth" "$role_oid=critical,ASN1:UTF8String:operate"
leaf critical-other plc-5 ca "extendedKeyUsage=clientAuth" "$role_oid=ASN1:UTF8String:operate" \
  "1.3.6.1.4.1.99999.1=critical,ASN1:UTF8String:unknown"

# Expired: `openssl x509` cannot back-date, `openssl ca` can (-startdate/-enddate).
key expired
openssl req -new -key expired.key -out expired.csr -subj "/O=Test Plant/CN=plc-old" 2>/dev/null
: > index.txt
echo 1000 > serial
cat > ca.cnf <<'EOF'
[ca]
default_ca = plant_ca
[plant_ca]
database = ./index.txt
new_certs_dir = .
serial = ./serial
default_md = sha256
policy = any
unique_subject = no
[any]
commonName = supplied
organizationName = optional
[client]
basicConstraints = CA:FALSE
extendedKeyUsage = clientAuth
EOF
echo "$role_oid = ASN1:UTF8String:operate" >> ca.cnf
openssl ca -batch -config ca.cnf -cert ca.crt -keyfile ca.key -in expired.csr -out expired.crt \
  -startdate 20200101000000Z -enddate 20200201000000Z -extensions client -notext 2>/dev/null
