"""The fixture of the browser tests: sms-sim on a pty with its control socket, the real
sms-gateway on it with the console on a free loopback port, users made with
`sms-gateway hash-password`, and a headless Chromium driven by Selenium (Debian chromium,
chromium-driver, python3-selenium). One gateway and one browser per test module."""
import base64
import http.client
import json
import os
import shutil
import struct
import threading
import socket
import subprocess
import sys
import tempfile
import time
import unittest

PASSWORD = "correct horse battery"
USERS = {"eng": "engineer", "op": "operate", "viewer": "read"}


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# How long a login may take: the password check runs on a worker at nice 10 (so that a flood of
# logins never delays the e-stop), which a loaded machine serves last.
LOGIN_TIMEOUT = 60


def wait_until(predicate, timeout=5.0, step=0.05, what="condition"):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(step)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r})")


class Simulator:
    """sms-sim with --control: its own state is the witness of what reached the servos."""

    def __init__(self, bin_dir, workdir, ids, name="sim", extra=()):
        self.link = os.path.join(workdir, "tty-" + name)
        self.control = os.path.join(workdir, name + ".sock")
        self.process = subprocess.Popen([os.path.join(bin_dir, "sms-sim"), "--ids", ids, "--link", self.link,
                                         "--control", self.control, *extra],
                                        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.process.stdout.readline()  # the pty path: the bus is up
        wait_until(lambda: os.path.exists(self.control), what="the simulator's control socket")

    def command(self, line):
        with socket.socket(socket.AF_UNIX) as s:
            s.settimeout(5)
            s.connect(self.control)
            s.sendall((line + "\n").encode())
            reply = b""
            while not reply.endswith(b"\n"):
                chunk = s.recv(4096)
                if not chunk:
                    break
                reply += chunk
        return reply.decode().strip()

    def field(self, servo, name):
        reply = self.command(f"field {servo} {name}")
        return int(reply)

    def stop(self):
        self.process.terminate()
        self.process.wait(10)


class GatewayCase(unittest.TestCase):
    """setUpClass starts the simulator and the gateway with its console once for the module's tests
    (no browser: tests that speak the console's HTTP and WebSocket API themselves)."""

    servo_ids = "1-3"
    sim_options = ()  # more sms-sim options, e.g. ("--no-timing",)
    # More keys of bus `arm`, e.g. ", watchdog: {timeout_ms: 300, feed: heartbeat_register}". A
    # response timeout a loaded machine meets (tests/README.md "Counting on a loaded machine").
    bus_yaml = ", response_timeout_ms: 200"
    extra_yaml = ""
    users = USERS    # console.users: name -> role, each with the password PASSWORD

    @classmethod
    def setUpClass(cls):
        cls.bin_dir = os.environ["SMS_BIN_DIR"]
        cls.workdir = tempfile.mkdtemp(prefix="sms-console-")
        cls.sim = Simulator(cls.bin_dir, cls.workdir, cls.servo_ids, extra=cls.sim_options)
        # A second line no bus owns, for the commissioning page: servos 4 and 9 at 115200 bit/s.
        cls.free_line = Simulator(cls.bin_dir, cls.workdir, "4,9", "free", ("--baud", "115200"))
        cls.modbus_port = free_port()
        cls.console_port = free_port()
        hashes = {}
        for user in cls.users:
            hashes[user] = subprocess.run([os.path.join(cls.bin_dir, "sms-gateway"), "hash-password"], input=PASSWORD + "\n",
                                          capture_output=True, text=True, check=True).stdout.strip()
        ids = [int(i) for i in cls.servo_ids.split("-")]
        servos = "".join(f"  - {{bus: arm, id: {i}, table: sts}}\n" for i in range(ids[0], ids[-1] + 1))
        users = "".join(f"    - {{name: {u}, role: {r}, password_hash: \"{hashes[u]}\"}}\n" for u, r in cls.users.items())
        config = (f"modbus_tcp: {{listen: \"127.0.0.1:{cls.modbus_port}\"}}\n"
                  f"buses:\n  - {{name: arm, device: \"{cls.sim.link}\", protocol: feetech, baud: 1000000{cls.bus_yaml}}}\n"
                  f"servos:\n{servos}"
                  f"state_dir: \"{cls.workdir}\"\n"
                  f"console:\n  listen: \"127.0.0.1:{cls.console_port}\"\n  users:\n{users}" + cls.extra_yaml)
        cls.config_path = os.path.join(cls.workdir, "cell.yaml")
        with open(cls.config_path, "w") as f:
            f.write(config)
        cls.log = open(os.path.join(cls.workdir, "gateway.log"), "w")
        cls.gateway = subprocess.Popen([os.path.join(cls.bin_dir, "sms-gateway"), "--config", cls.config_path],
                                       stdout=cls.log, stderr=subprocess.STDOUT)
        cls.base = f"http://127.0.0.1:{cls.console_port}"
        wait_until(cls._console_up, timeout=15, what="the console to listen")

    @classmethod
    def _console_up(cls):
        if cls.gateway.poll() is not None:
            raise AssertionError("sms-gateway exited: " + open(os.path.join(cls.workdir, "gateway.log")).read())
        try:
            with socket.create_connection(("127.0.0.1", cls.console_port), timeout=0.2):
                return True
        except OSError:
            return False

    @classmethod
    def tearDownClass(cls):
        if hasattr(cls, "gateway"):
            cls.gateway.terminate()
            try:
                cls.gateway.wait(15)
            except subprocess.TimeoutExpired:
                cls.gateway.kill()
            cls.log.close()
            if cls.gateway.returncode != 0:
                sys.stderr.write(open(os.path.join(cls.workdir, "gateway.log")).read())
        for sim in ("sim", "free_line"):
            if hasattr(cls, sim):
                getattr(cls, sim).stop()
        if os.environ.get("SMS_CONSOLE_KEEP"):  # for a look at gateway.log after a failure
            sys.stderr.write(f"kept {cls.workdir}\n")
        else:
            shutil.rmtree(cls.workdir, ignore_errors=True)

    def modbus(self):
        from pymodbus.client import ModbusTcpClient
        client = ModbusTcpClient("127.0.0.1", port=self.modbus_port, timeout=3)
        self.assertTrue(client.connect(), "cannot connect to the gateway's Modbus TCP port")
        return client

    def api_login(self, user):
        """Logs `user` in over the JSON API: (the session cookie, its CSRF token)."""
        connection = http.client.HTTPConnection("127.0.0.1", self.console_port, timeout=LOGIN_TIMEOUT)
        connection.request("POST", "/api/login", json.dumps({"user": user, "password": PASSWORD}),
                           {"Content-Type": "application/json"})
        answer = connection.getresponse()
        body = json.loads(answer.read())
        self.assertEqual(answer.status, 200, body)
        cookie = answer.getheader("Set-Cookie").split(";")[0]
        connection.close()
        return cookie, body["csrf"]


class ConsoleCase(GatewayCase):
    """setUpClass starts the simulator, the gateway and Chromium once for the module's tests."""

    @classmethod
    def setUpClass(cls):
        if shutil.which("chromedriver") is None or not os.path.exists("/usr/bin/chromium"):
            raise unittest.SkipTest("chromium and chromium-driver are not installed (scripts/install-deps.sh installs them)")
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        super().setUpClass()
        options = webdriver.ChromeOptions()
        options.binary_location = "/usr/bin/chromium"
        for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                         "--window-size=1400,1000", "--disable-background-timer-throttling"):
            options.add_argument(argument)
        cls.browser = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
        # Downloads (the plot's CSV) land in the test's own folder.
        cls.downloads = os.path.join(cls.workdir, "downloads")
        os.makedirs(cls.downloads)
        cls.browser.execute_cdp_cmd("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": cls.downloads})
        cls.browser.set_page_load_timeout(20)
        cls.browser.set_script_timeout(10)

    @classmethod
    def tearDownClass(cls):
        if hasattr(cls, "browser"):
            cls.browser.quit()
        super().tearDownClass()

    # --- browser helpers ---------------------------------------------------------------------------

    def login(self, user):
        from selenium.webdriver.common.by import By
        self.browser.delete_all_cookies()
        self.browser.get(self.base + "/login")
        self.browser.find_element(By.ID, "user").send_keys(user)
        self.browser.find_element(By.ID, "password").send_keys(PASSWORD)
        self.browser.find_element(By.ID, "submit").click()
        wait_until(lambda: self.browser.current_url.rstrip("/") == self.base, timeout=LOGIN_TIMEOUT,
                   what=f"{user} to be logged in")

    def open(self, path, ready_css):
        from selenium.webdriver.common.by import By
        self.browser.get(self.base + path)
        return wait_until(lambda: self.browser.find_elements(By.CSS_SELECTOR, ready_css), timeout=10,
                          what=f"{ready_css} on {path}")

    def screenshot(self, name):
        folder = os.environ.get("SMS_CONSOLE_SCREENSHOTS")
        if folder:
            os.makedirs(folder, exist_ok=True)
            self.browser.save_screenshot(os.path.join(folder, name))


class ConsoleSocket:
    """A page's WebSocket to the console (RFC 6455, text frames; Python's standard library has no
    client): every JSON message the gateway pushes is kept, in order; send() is thread-safe."""

    def __init__(self, port, path, cookie, csrf):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET {path}?csrf={csrf} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"Cookie: {cookie}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                raise AssertionError(f"the console closed the WebSocket {path} during the handshake: {head!r}")
            head += chunk
        if not head.startswith(b"HTTP/1.1 101"):
            raise AssertionError(f"WebSocket {path} refused: {head!r}")
        self.sock.settimeout(None)
        self.messages = []
        self.closed = False
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _exactly(self, count):
        data = b""
        while len(data) < count:
            chunk = self.sock.recv(count - len(data))
            if not chunk:
                raise EOFError
            data += chunk
        return data

    def _read(self):
        try:
            while True:
                first, second = self._exactly(2)
                length = second & 0x7F
                if length == 126:
                    length = struct.unpack("!H", self._exactly(2))[0]
                elif length == 127:
                    length = struct.unpack("!Q", self._exactly(8))[0]
                payload = self._exactly(length)
                opcode = first & 0x0F
                if opcode == 0x8:
                    break
                if opcode == 0x9:
                    self._frame(0xA, payload)
                elif opcode == 0x1:
                    with self._lock:
                        self.messages.append(json.loads(payload))
        except (EOFError, OSError):
            pass
        self.closed = True

    def _frame(self, opcode, payload):
        mask = os.urandom(4)
        header = bytes([0x80 | opcode])
        if len(payload) < 126:
            header += bytes([0x80 | len(payload)])
        else:
            header += bytes([0x80 | 126]) + struct.pack("!H", len(payload))
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        with self._send_lock:
            self.sock.sendall(header + mask + masked)

    def send(self, message):
        self._frame(0x1, json.dumps(message).encode())

    def received(self):
        with self._lock:
            return list(self.messages)

    def close(self):
        try:
            self._frame(0x8, b"")
        except OSError:
            pass
        self.sock.close()
        self._reader.join(5)
