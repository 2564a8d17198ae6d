"""The console over HTTPS (console.tls: the Modbus/TCP Security certificate, key and CA; client
certificates give their roles), checked with Python's own TLS client against the real gateway
on sms-sim. Certificates come from tests/e2e/make_test_certs.sh."""
import http.client
import json
import os
import shutil
import socket
import ssl
import subprocess
import tempfile
import unittest

from console_support import Simulator, free_port, wait_until

HERE = os.path.dirname(os.path.abspath(__file__))


class ConsoleTlsTest(unittest.TestCase):

    @classmethod
    def setUpClass(cls):
        cls.bin_dir = os.environ["SMS_BIN_DIR"]
        cls.workdir = tempfile.mkdtemp(prefix="sms-console-tls-")
        cls.certs = os.path.join(cls.workdir, "certs")
        subprocess.run([os.path.join(HERE, "..", "e2e", "make_test_certs.sh"), cls.certs], check=True)
        cls.sim = Simulator(cls.bin_dir, cls.workdir, "1-2")
        cls.port = free_port()
        c = cls.certs
        config = (f"modbus_tcp:\n  listen: \"127.0.0.1:{free_port()}\"\n"
                  f"  tls: {{listen: \"127.0.0.1:{free_port()}\", certificate: {c}/server.crt, private_key: {c}/server.key, "
                  f"ca: {c}/ca.crt}}\n"
                  f"buses:\n  - {{name: arm, device: \"{cls.sim.link}\", protocol: feetech, baud: 1000000, response_timeout_ms: 200}}\n"
                  "servos:\n  - {bus: arm, id: 1, table: sts}\n  - {bus: arm, id: 2, table: sts}\n"
                  f"state_dir: \"{cls.workdir}\"\n"
                  f"console: {{listen: \"127.0.0.1:{cls.port}\", tls: true}}\n")
        path = os.path.join(cls.workdir, "cell.yaml")
        with open(path, "w") as f:
            f.write(config)
        cls.log = open(os.path.join(cls.workdir, "gateway.log"), "w")
        cls.gateway = subprocess.Popen([os.path.join(cls.bin_dir, "sms-gateway"), "--config", path],
                                       stdout=cls.log, stderr=subprocess.STDOUT)

        def up():
            if cls.gateway.poll() is not None:
                raise AssertionError(open(os.path.join(cls.workdir, "gateway.log")).read())
            try:
                with socket.create_connection(("127.0.0.1", cls.port), timeout=0.2):
                    return True
            except OSError:
                return False
        wait_until(up, timeout=15, what="the console to listen")

    @classmethod
    def tearDownClass(cls):
        cls.gateway.terminate()
        cls.gateway.wait(15)
        cls.log.close()
        cls.sim.stop()
        shutil.rmtree(cls.workdir, ignore_errors=True)

    def connection(self, certificate):
        context = ssl.create_default_context(cafile=os.path.join(self.certs, "ca.crt"))
        if certificate:
            context.load_cert_chain(os.path.join(self.certs, certificate + ".crt"), os.path.join(self.certs, certificate + ".key"))
        connection = http.client.HTTPSConnection("localhost", self.port, context=context, timeout=5)
        self.addCleanup(connection.close)
        return connection

    def request(self, connection, method, path, body=None, headers=None):
        connection.request(method, path, body=json.dumps(body) if body is not None else None, headers=headers or {})
        response = connection.getresponse()
        return response.status, response.getheader("Set-Cookie"), response.read().decode()

    def session(self, certificate):
        connection = self.connection(certificate)
        status, cookie, body = self.request(connection, "GET", "/api/session")
        self.assertEqual(status, 200, body)
        return connection, cookie.split(";")[0], json.loads(body)

    def test_a_client_certificate_gives_its_role(self):
        connection, cookie, me = self.session("operate")
        self.assertEqual(me["role"], "operate")
        self.assertIn("client certificate", me["how"])
        headers = {"Cookie": cookie, "X-CSRF-Token": me["csrf"], "Content-Type": "application/json"}
        status, _, body = self.request(connection, "POST", "/api/servo/1/write", {"field": "acceleration", "value": 21}, headers)
        self.assertEqual(status, 200, body)
        self.assertEqual(self.sim.field(1, "acceleration"), 21)
        # EEPROM needs engineer: refused, nothing written.
        status, _, body = self.request(connection, "POST", "/api/servo/1/write", {"field": "max_temperature", "value": 70}, headers)
        self.assertEqual(status, 403, body)

    def test_b_a_read_certificate_cannot_write(self):
        connection, cookie, me = self.session("read")
        self.assertEqual(me["role"], "read")
        headers = {"Cookie": cookie, "X-CSRF-Token": me["csrf"], "Content-Type": "application/json"}
        status, _, body = self.request(connection, "POST", "/api/estop", {"latch": True}, headers)
        self.assertEqual(status, 403, body)

    def test_c_the_session_cookie_is_secure_httponly_strict(self):
        _, _, _ = self.session("engineer")
        connection = self.connection("engineer")
        _, cookie, _ = self.request(connection, "GET", "/api/session")
        for flag in ("HttpOnly", "SameSite=Strict", "Secure"):
            self.assertIn(flag, cookie)

    def test_d_without_a_certificate_there_is_no_way_in(self):
        with self.assertRaises((ssl.SSLError, ConnectionResetError, BrokenPipeError)):
            self.request(self.connection(None), "GET", "/api/session")


if __name__ == "__main__":
    unittest.main(verbosity=2)
