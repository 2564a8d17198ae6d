#!/usr/bin/python3
"""How the gateway's TLS listener ends a connection, seen by Python's ssl module (OpenSSL under
an independent client): with close_notify, so a client can tell the end from a cut connection.

  tls_close_notify.py PORT CERTS_DIR CASE

CASE is one of
  client-closes  a certified client reads once, then says close_notify: the gateway answers it
                 (SSLSocket.unwrap() returns; without the gateway's alert it raises)
  no-role        a certificate without a role: the gateway refuses it after the handshake and
                 its close comes with close_notify (recv() returns b'', not SSLEOFError)
  idle           a certified client that stays silent past the idle timeout: the same
Prints what happened; exit 0 when the close came with close_notify."""
import socket
import ssl
import sys

port, certs, case = int(sys.argv[1]), sys.argv[2], sys.argv[3]
name = "norole" if case == "no-role" else "read"
context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
context.load_verify_locations(f"{certs}/ca.crt")
context.load_cert_chain(f"{certs}/{name}.crt", f"{certs}/{name}.key")
# Python sets OP_IGNORE_UNEXPECTED_EOF by default (OpenSSL 3 then reads a cut connection as a
# clean end): off, so a close without close_notify raises SSLEOFError.
context.options &= ~ssl.OP_IGNORE_UNEXPECTED_EOF
# TLS 1.2 for the client's own close_notify case: the case the gateway got wrong was 1.2's.
if case == "client-closes":
    context.maximum_version = ssl.TLSVersion.TLSv1_2
raw = socket.create_connection(("127.0.0.1", port), timeout=10)
# A close without close_notify must raise, not read as an empty string.
tls = context.wrap_socket(raw, server_hostname="localhost", suppress_ragged_eofs=False)
print("connected:", tls.version())
try:
    if case == "client-closes":
        # FC04 of the gateway unit: input register 5 (the number of buses).
        tls.sendall(bytes([0, 1, 0, 0, 0, 6, 255, 4, 0, 5, 0, 1]))
        answer = tls.recv(64)
        print("answer:", answer.hex())
        tls.unwrap()  # sends ours and waits for the gateway's
        print("the gateway answered close_notify")
    else:
        if case == "no-role":
            tls.sendall(bytes([0, 1, 0, 0, 0, 6, 255, 4, 0, 5, 0, 1]))
        data = tls.recv(64)
        if data != b"":
            print("unexpected data:", data.hex())
            sys.exit(1)
        print("closed with close_notify")
except ssl.SSLEOFError as error:
    print("closed without close_notify:", error)
    sys.exit(1)
except (ssl.SSLError, OSError) as error:
    print("failed:", type(error).__name__, error)
    sys.exit(1)
