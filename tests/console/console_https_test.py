"""The console's own HTTPS (console.certificate and console.key, docs/CONSOLE.md "HTTPS"), checked
with Python's TLS client against the real gateway on sms-sim: password users log in over TLS with
a self-signed pair made the way the Debian package makes it; a console with users on a
non-loopback address and no HTTPS does not start, from the file or from --console, unless
insecure_http says so, and then every start warns; every end the console chooses comes with
close_notify."""
import http.client
import json
import os
import shutil
import socket
import ssl
import subprocess
import tempfile
import unittest

from console_support import LOGIN_TIMEOUT, PASSWORD, Simulator, free_port, wait_until


def read(path):
    with open(path) as f:
        return f.read()


def make_pair(directory, name):
    """A self-signed certificate and key, as debian/sms-gateway.postinst makes them."""
    key, certificate = os.path.join(directory, name + ".key"), os.path.join(directory, name + ".crt")
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                    "-days", "30", "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost",
                    "-keyout", key, "-out", certificate], check=True, capture_output=True)
    os.chmod(key, 0o640)
    return certificate, key


class ConsoleHttpsTest(unittest.TestCase):

    @classmethod
    def setUpClass(cls):
        cls.bin_dir = os.environ["SMS_BIN_DIR"]
        cls.workdir = tempfile.mkdtemp(prefix="sms-console-https-")
        cls.certificate, cls.key = make_pair(cls.workdir, "console")
        cls.other_certificate, cls.other_key = make_pair(cls.workdir, "other")
        cls.hash = subprocess.run([os.path.join(cls.bin_dir, "sms-gateway"), "hash-password"], input=PASSWORD + "\n",
                                  capture_output=True, text=True, check=True).stdout.strip()
        cls.sim = Simulator(cls.bin_dir, cls.workdir, "1")
        cls.port = free_port()
        cls.gateway, cls.log_path = cls.start(
            f"console:\n  listen: \"127.0.0.1:{cls.port}\"\n  certificate: {cls.certificate}\n  key: {cls.key}\n",
            "https")
        wait_until(lambda: cls.listening(cls.gateway, cls.log_path, cls.port), timeout=15, what="the console to listen")

    @classmethod
    def start(cls, console_yaml, name, *options, mode=0o640, device=None):
        config = (f"modbus_tcp: {{listen: \"127.0.0.1:{free_port()}\"}}\n"
                  f"buses:\n  - {{name: arm, device: \"{device or cls.sim.link}\", protocol: feetech, baud: 1000000, response_timeout_ms: 200}}\n"
                  "servos:\n  - {bus: arm, id: 1, table: sts}\n"
                  f"state_dir: \"{cls.workdir}\"\n" + console_yaml +
                  f"  users:\n    - {{name: op, role: operate, password_hash: \"{cls.hash}\"}}\n")
        path = os.path.join(cls.workdir, name + ".yaml")
        with open(path, "w") as f:
            f.write(config)
        os.chmod(path, mode)
        log_path = os.path.join(cls.workdir, name + ".log")
        with open(log_path, "w") as log:
            process = subprocess.Popen([os.path.join(cls.bin_dir, "sms-gateway"), "--config", path, *options],
                                       stdout=log, stderr=subprocess.STDOUT)
        return process, log_path

    @staticmethod
    def listening(process, log_path, port):
        if process.poll() is not None:
            raise AssertionError(f"sms-gateway exited ({process.returncode}): " + read(log_path))
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return True
        except OSError:
            return False

    @staticmethod
    def stop(process):
        process.terminate()
        try:
            process.wait(15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    @classmethod
    def tearDownClass(cls):
        if hasattr(cls, "gateway"):
            cls.stop(cls.gateway)
        cls.sim.stop()
        if os.environ.get("SMS_CONSOLE_KEEP"):
            print(f"kept {cls.workdir}")
        else:
            shutil.rmtree(cls.workdir, ignore_errors=True)

    def https(self):
        context = ssl.create_default_context(cafile=self.certificate)  # its own certificate, trusted as is
        connection = http.client.HTTPSConnection("localhost", self.port, context=context, timeout=LOGIN_TIMEOUT)
        self.addCleanup(connection.close)
        return connection

    def test_login_over_https(self):
        connection = self.https()
        connection.request("POST", "/api/login", json.dumps({"user": "op", "password": PASSWORD}),
                           {"Content-Type": "application/json"})
        answer = connection.getresponse()
        body = json.loads(answer.read())
        self.assertEqual(answer.status, 200, body)
        cookie = answer.getheader("Set-Cookie")
        self.assertIn("; Secure", cookie)
        self.assertIn("; HttpOnly", cookie)
        connection.request("GET", "/api/session", headers={"Cookie": cookie.split(";")[0]})
        answer = connection.getresponse()
        self.assertEqual(json.loads(answer.read())["user"], "op")
        self.assertIn(f"serving the browser console on https://127.0.0.1:{self.port}/", read(self.log_path))

    def raw_tls(self, maximum=None):
        """A TLS socket on which a close without close_notify raises SSLEOFError (Python's default,
        OP_IGNORE_UNEXPECTED_EOF, would read it as a clean end)."""
        context = ssl.create_default_context(cafile=self.certificate)
        context.options &= ~ssl.OP_IGNORE_UNEXPECTED_EOF
        if maximum:
            context.maximum_version = maximum
        raw = socket.create_connection(("127.0.0.1", self.port), timeout=20)
        tls = context.wrap_socket(raw, server_hostname="localhost", suppress_ragged_eofs=False)
        self.addCleanup(tls.close)
        return tls

    @staticmethod
    def read_to_close_notify(tls):
        """Everything until the console's close_notify; SSLEOFError if the close came without one."""
        received = b""
        while True:
            data = tls.recv(4096)
            if not data:
                return received
            received += data

    def test_connection_close_ends_with_close_notify(self):
        tls = self.raw_tls()
        tls.sendall(b"GET /login HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
        received = self.read_to_close_notify(tls)
        self.assertTrue(received.startswith(b"HTTP/1.1 200"), received[:200])

    def test_clients_close_notify_is_answered(self):
        tls = self.raw_tls(ssl.TLSVersion.TLSv1_2)  # the version whose client-first close was got wrong before
        tls.sendall(b"GET /login HTTP/1.1\r\nHost: localhost\r\n\r\n")
        head = b""
        while b"\r\n\r\n" not in head:
            head += tls.recv(4096)
        self.assertTrue(head.startswith(b"HTTP/1.1 200"), head[:200])
        tls.unwrap()  # sends ours and waits for the console's: raises without it

    def test_silent_client_is_closed_with_close_notify(self):
        # Past the door's first-request deadline (5 s) the console closes it, saying so.
        tls = self.raw_tls()
        self.assertEqual(self.read_to_close_notify(tls), b"")

    def test_plain_http_gets_no_page(self):
        connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
        self.addCleanup(connection.close)
        with self.assertRaises((http.client.HTTPException, OSError)):
            connection.request("GET", "/login")
            connection.getresponse().read()

    def test_users_off_loopback_without_https_do_not_start(self):
        port = free_port()
        process, log_path = self.start(f"console:\n  listen: \"0.0.0.0:{port}\"\n", "plain")
        self.assertEqual(process.wait(30), 2, read(log_path))
        log = read(log_path)
        self.assertIn(f"console.listen: 0.0.0.0:{port} is reachable from other machines and the console's users log "
                      "in with passwords", log)
        self.assertIn("console.certificate and console.key", log)

    def test_console_option_off_loopback_without_https_does_not_start(self):
        process, log_path = self.start(f"console:\n  listen: \"127.0.0.1:{free_port()}\"\n", "option",
                                       "--console", f"0.0.0.0:{free_port()}")
        self.assertEqual(process.wait(30), 2, read(log_path))
        self.assertIn("which plain HTTP would carry in clear", read(log_path))

    def start_and_stop(self, console_yaml, name, port, mode=0o640):
        """Runs a second gateway (on a simulator of its own) until its console listens; its log."""
        sim = Simulator(self.bin_dir, self.workdir, "1", name + "-sim")
        self.addCleanup(sim.stop)
        process, log_path = self.start(console_yaml, name, mode=mode, device=sim.link)
        try:
            wait_until(lambda: self.listening(process, log_path, port), timeout=15, what=f"the console of {name}")
        finally:
            self.stop(process)
        return read(log_path)

    def test_insecure_http_starts_with_a_warning_every_time(self):
        for start in (1, 2):
            port = free_port()
            log = self.start_and_stop(f"console:\n  listen: \"0.0.0.0:{port}\"\n  insecure_http: true\n",
                                      f"insecure-{start}", port)
            self.assertIn("console: passwords of console.users cross the network in clear: "
                          f"http://0.0.0.0:{port}/ is plain HTTP on a non-loopback address "
                          "(console.insecure_http: true)", log, f"start {start}")

    def test_secret_files_readable_by_others_are_named_at_start(self):
        # The running gateway's files are 0640: no such warning (it was logged before the console listened).
        self.assertNotIn("by every user of this machine", read(self.log_path))
        key = os.path.join(self.workdir, "open.key")
        shutil.copy(self.key, key)
        os.chmod(key, 0o644)
        port = free_port()
        log = self.start_and_stop(f"console:\n  listen: \"127.0.0.1:{port}\"\n  certificate: {self.certificate}\n"
                                  f"  key: {key}\n", "open", port, mode=0o644)
        config = os.path.join(self.workdir, "open.yaml")
        self.assertIn(f"configuration file {config} holds console password hashes (console.users) and is readable by "
                      f"every user of this machine (mode 0644): chmod 0640 {config} && chown root:", log)
        self.assertIn(f"console.key {key} is a private key and is readable by every user of this machine (mode 0644): "
                      f"chmod 0640 {key} && chown root:", log)

    def test_a_key_of_another_certificate_does_not_start(self):
        process, log_path = self.start(f"console:\n  listen: \"127.0.0.1:{free_port()}\"\n  certificate: "
                                       f"{self.certificate}\n  key: {self.other_key}\n", "mismatch")
        self.assertNotEqual(process.wait(30), 0)
        self.assertIn(f"console.key {self.other_key} does not belong to {self.certificate}", read(log_path))

    def test_a_missing_certificate_does_not_start(self):
        missing = os.path.join(self.workdir, "nosuch.crt")
        process, log_path = self.start(f"console:\n  listen: \"127.0.0.1:{free_port()}\"\n  certificate: {missing}\n"
                                       f"  key: {self.key}\n", "missing")
        self.assertNotEqual(process.wait(30), 0)
        self.assertIn(f"console.certificate {missing}: cannot open: No such file or directory", read(log_path))


if __name__ == "__main__":
    unittest.main()
