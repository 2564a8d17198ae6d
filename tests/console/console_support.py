"""The fixture of the browser tests: sms-sim on a pty with its control socket, the real
sms-gateway on it with the console on a free loopback port, users made with
`sms-gateway hash-password`, and a headless Chromium driven by Selenium (Debian chromium,
chromium-driver, python3-selenium). One gateway and one browser per test module."""
import os
import shutil
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


class ConsoleCase(unittest.TestCase):
    """setUpClass starts the simulator, the gateway and Chromium once for the module's tests."""

    servo_ids = "1-3"
    extra_yaml = ""

    @classmethod
    def setUpClass(cls):
        if shutil.which("chromedriver") is None or not os.path.exists("/usr/bin/chromium"):
            raise unittest.SkipTest("chromium and chromium-driver are not installed (scripts/install-deps.sh installs them)")
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        cls.bin_dir = os.environ["SMS_BIN_DIR"]
        cls.workdir = tempfile.mkdtemp(prefix="sms-console-")
        cls.sim = Simulator(cls.bin_dir, cls.workdir, cls.servo_ids)
        # A second line no bus owns, for the commissioning page: servos 4 and 9 at 115200 bit/s.
        cls.free_line = Simulator(cls.bin_dir, cls.workdir, "4,9", "free", ("--baud", "115200"))
        cls.modbus_port = free_port()
        cls.console_port = free_port()
        hashes = {}
        for user in USERS:
            hashes[user] = subprocess.run([os.path.join(cls.bin_dir, "sms-gateway"), "hash-password"], input=PASSWORD + "\n",
                                          capture_output=True, text=True, check=True).stdout.strip()
        ids = [int(i) for i in cls.servo_ids.split("-")]
        servos = "".join(f"  - {{bus: arm, id: {i}, table: sts}}\n" for i in range(ids[0], ids[-1] + 1))
        users = "".join(f"    - {{name: {u}, role: {r}, password_hash: \"{hashes[u]}\"}}\n" for u, r in USERS.items())
        config = (f"modbus_tcp: {{listen: \"127.0.0.1:{cls.modbus_port}\"}}\n"
                  f"buses:\n  - {{name: arm, device: \"{cls.sim.link}\", protocol: feetech, baud: 1000000}}\n"
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
        if hasattr(cls, "browser"):
            cls.browser.quit()
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

    # --- browser helpers ---------------------------------------------------------------------------

    def login(self, user):
        from selenium.webdriver.common.by import By
        self.browser.delete_all_cookies()
        self.browser.get(self.base + "/login")
        self.browser.find_element(By.ID, "user").send_keys(user)
        self.browser.find_element(By.ID, "password").send_keys(PASSWORD)
        self.browser.find_element(By.ID, "submit").click()
        wait_until(lambda: self.browser.current_url.rstrip("/") == self.base, what=f"{user} to be logged in")

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

    def modbus(self):
        from pymodbus.client import ModbusTcpClient
        client = ModbusTcpClient("127.0.0.1", port=self.modbus_port, timeout=3)
        self.assertTrue(client.connect(), "cannot connect to the gateway's Modbus TCP port")
        return client
