"""The browser console end to end: real pages in headless Chromium against the real gateway on
sms-sim (docs/CONSOLE.md). Witnesses are the simulator's own state (its control socket) and an
independent Modbus client (pymodbus)."""
import base64
import json
import os
import shutil
import subprocess
import time
import unittest

from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By

from console_support import ConsoleCase, wait_until


class ConsoleTest(ConsoleCase):

    def test_a_overview_lists_the_servos_live(self):
        self.login("eng")
        self.open("/", "#servos-table tr[data-unit='3'] td.online")
        # The tables are redrawn on every push: read them in one go from the page.
        units = self.browser.execute_script(
            "return [...document.querySelectorAll('#servos-table tr[data-unit]')].map(r => r.dataset.unit)")
        self.assertEqual(units, ["1", "2", "3"])
        # Discovery may still be going on a loaded machine: the row comes before servo 3 is found.
        wait_until(lambda: "3 / 3" in self.text("#buses-table tr[data-bus='arm']"),
                   what="bus arm to show its 3 servos found")
        # Live: a position changed on the wire shows without a reload.
        self.sim.command("set 1 42 00 04")  # servo 1's goal := 1024 through the simulator's backdoor
        position = "#servos-table tr[data-unit='1'] td.position"  # "1024 steps": the table's unit
        wait_until(lambda: abs(int(self.text(position).split(" ")[0] or 0) - 1024) < 5,
                   timeout=10, what="servo 1's position to reach 1024 on the overview")
        self.screenshot("overview.png")

    def test_b_editing_a_field_changes_the_simulator(self):
        self.login("eng")
        self.open("/servo/2", "#field-acceleration input.edit")
        field = self.browser.find_element(By.CSS_SELECTOR, "#field-acceleration input.edit")
        field.send_keys("37")
        self.browser.find_element(By.CSS_SELECTOR, "#field-acceleration button.write").click()
        wait_until(lambda: self.sim.field(2, "acceleration") == 37, what="the simulator's acceleration of servo 2 to be 37")
        wait_until(lambda: "written" in self.text("#message"), what="the page to say it was written")
        wait_until(lambda: self.text("#field-acceleration td.raw") == "37", what="the table to read 37 back")
        self.assertEqual(self.text("#field-acceleration td.value"), "3700 steps/s²")  # the table's 100 steps/s²
        # Out of range: a clear message, nothing written.
        field = self.browser.find_element(By.CSS_SELECTOR, "#field-acceleration input.edit")
        field.send_keys("9999")
        self.browser.find_element(By.CSS_SELECTOR, "#field-acceleration button.write").click()
        message = wait_until(lambda: self.browser.find_element(By.ID, "message").text, what="a message")
        self.assertIn("outside", message)
        # The server refuses it too, whatever the page checks.
        answer = self.fetch("POST", "/api/servo/2/write", {"field": "acceleration", "value": 9999})
        self.assertEqual(answer["status"], 400, answer)
        self.assertIn("nothing written", answer["body"])
        self.assertEqual(self.sim.field(2, "acceleration"), 37)

    def test_c_plot_follows_a_modbus_client_moving_the_servo(self):
        self.login("op")
        self.open("/servo/2", "#plot[data-samples]")
        client = self.modbus()
        start = self.sim.field(2, "present_position")
        goal = 3500 if start < 2500 else 500
        self.write_goal(client, 2, goal)
        client.close()

        def plotted_near_goal():
            data = self.browser.execute_script(
                "const c = Chart.getChart('plot'); return c.data.datasets.length ? c.data.datasets[0].data.map(p => p.y) : [];")
            return data and abs(data[-1] - goal) < 10 and any(abs(y - start) < 10 for y in data)
        wait_until(plotted_near_goal, timeout=10, what="the plot to show the move from start to goal")
        self.screenshot("servo-plot.png")

    def test_c_2_bus_monitor_shows_the_frames_of_a_write(self):
        self.login("eng")
        self.open("/", "#buses-table tr[data-bus='arm'] a")
        # The overview links the bus to its monitor (read in one go: the table is redrawn on every push).
        href = self.browser.execute_script("return document.querySelector(\"#buses-table tr[data-bus='arm'] a\").getAttribute('href')")
        self.assertEqual(href, "/bus/arm/monitor")
        self.open("/bus/arm/monitor", "#frames tbody tr.frame")  # the poll's frames flow at once
        # Only servo 3's frames from now on (the gateway filters).
        servo = self.browser.find_element(By.ID, "servo")
        servo.send_keys("3")
        servo.send_keys("\t")
        client = self.modbus()
        goal = 1500 if self.sim.field(3, "goal_position") != 1500 else 2500
        self.write_goal(client, 3, goal)
        client.close()

        def rows():
            return self.browser.execute_script(
                "return [...document.querySelectorAll('#frames tbody tr.frame')].map(r => ({servo: r.dataset.servo, "
                "kind: r.dataset.kind, instruction: r.querySelector('.instruction').textContent, "
                "fields: r.querySelector('.fields').textContent}))")
        write = wait_until(lambda: [r for r in rows() if r["kind"] == "request" and r["instruction"] == "WRITE"
                                    and f"goal_position={goal}" in r["fields"]],
                           timeout=10, what="the WRITE of servo 3's goal_position on the monitor")
        self.assertEqual(write[0]["servo"], "3")
        wait_until(lambda: [r for r in rows() if r["kind"] == "answer" and "WRITE" in r["instruction"]],
                   timeout=10, what="servo 3's answer to the WRITE on the monitor")
        self.screenshot("bus-monitor.png")
        # The filter holds: after a clear, only servo 3's frames come (254: a SYNC frame it is part of).
        self.browser.find_element(By.ID, "clear").click()
        wait_until(lambda: len(rows()) >= 4, timeout=10, what="servo 3's poll frames after the clear")
        self.assertTrue(all(r["servo"] in ("3", "254") for r in rows()), rows())
        # The capture download opens in Wireshark's tshark, whose Lua dissector (shipped in the
        # package) names the instruction and the ID.
        encoded = self.browser.execute_async_script("""
            const done = arguments[0];
            fetch('/api/bus/arm/monitor.pcapng').then(r => r.arrayBuffer()).then(buffer => {
              let text = ''; const bytes = new Uint8Array(buffer);
              for (let i = 0; i < bytes.length; i += 8192) text += String.fromCharCode(...bytes.subarray(i, i + 8192));
              done(btoa(text));
            });""")
        capture = os.path.join(self.workdir, "arm.pcapng")
        with open(capture, "wb") as f:
            f.write(base64.b64decode(encoded))
        if shutil.which("tshark") is None:
            self.skipTest("tshark is not installed (scripts/install-deps.sh installs it)")
        dissector = os.path.join(os.path.dirname(__file__), "..", "..", "deploy", "wireshark", "sms_servo.lua")
        fields = subprocess.run(["tshark", "-X", "lua_script:" + dissector, "-r", capture,
                                 "-Y", 'sms_servo.instruction_name == "WRITE" && sms_servo.id == 3',
                                 "-T", "fields", "-e", "sms_servo.id", "-e", "sms_servo.instruction_name"],
                                capture_output=True, text=True, timeout=60)
        self.assertEqual(fields.returncode, 0, fields.stderr)
        self.assertIn("3\tWRITE", fields.stdout, fields.stdout + fields.stderr)

    def hold(self, servo, release=True, button="hold-position"):
        """Presses the hold-to-run button and holds it until the simulator shows the servo moving
        (20 steps from where it was): as long as a loaded machine takes, not a fixed time, after
        which a slow page or gateway would have moved nothing yet."""
        before = self.sim.field(servo, "present_position")
        ActionChains(self.browser).click_and_hold(self.browser.find_element(By.ID, button)).perform()
        try:
            wait_until(lambda: abs(self.sim.field(servo, "present_position") - before) > 20,
                       what=f"the held button to move servo {servo}")
        finally:
            if release:
                ActionChains(self.browser).release().perform()

    def stopped_by_the_gateway(self, servo, far_goal):
        """The servo's safe stop reached it: its hold (a goal other than the jog's far one), or the
        torque off a stop writes when the servo's state could not be read."""
        return self.sim.field(servo, "goal_position") != far_goal or self.sim.field(servo, "torque_enable") == 0

    def wait_stopped(self, servo, timeout=15):
        """The servo's position stays put for 300 ms (the simulator's own motion model)."""
        def still():
            first = self.sim.field(servo, "present_position")
            time.sleep(0.3)
            return first == self.sim.field(servo, "present_position")
        wait_until(still, timeout=timeout, what=f"servo {servo} to stand still")

    def start_far_move(self, servo):
        self.open(f"/servo/{servo}", "#hold-position:not([disabled])")
        wait_until(lambda: self.browser.execute_script("return document.getElementById('link-state').textContent") == "live",
                   what="the page's WebSocket")
        start = self.sim.field(servo, "present_position")
        goal = 4000 if start < 2048 else 100
        box = self.browser.find_element(By.ID, "jog-position")
        box.clear()
        box.send_keys(str(goal))
        return start, goal

    def test_d_hold_to_run_stops_when_released(self):
        self.login("op")
        self.sim.command("set 3 41 0a")  # a slow acceleration, so the move outlasts the hold
        start, goal = self.start_far_move(3)
        self.hold(3)
        # The release writes the servo's safe stop where it is: the goal is no longer the far one (or,
        # had the servo not answered the stop's read on a loaded machine, its torque is off).
        wait_until(lambda: self.stopped_by_the_gateway(3, goal), timeout=15, what="the release to end the jog")
        self.wait_stopped(3)
        stopped = self.sim.field(3, "present_position")
        self.assertNotEqual(stopped, start, "the servo did not move while the button was held")
        self.assertGreater(abs(goal - stopped), 200, "the servo ran on to its goal after the release")
        if self.sim.field(3, "torque_enable") == 1:  # held, not let go
            self.assertLess(abs(self.sim.field(3, "goal_position") - stopped), 50, "the goal was not held at the position")

    def test_e_hold_to_run_stops_when_the_tab_closes(self):
        self.login("op")
        self.sim.command("set 1 41 0a")  # a slow acceleration, so the move outlasts the hold
        main_window = self.browser.current_window_handle
        self.browser.switch_to.new_window("tab")
        start, goal = self.start_far_move(1)
        self.hold(1, release=False)  # still held when the tab goes
        self.browser.close()
        self.browser.switch_to.window(main_window)
        # The witness is the servo's own goal: the gateway ends the jog when the tab's socket goes,
        # writing a hold where the servo is; without it the goal stays the far one until arrival.
        wait_until(lambda: self.stopped_by_the_gateway(1, goal), timeout=15,
                   what="the gateway to end the jog of the closed tab")
        self.wait_stopped(1)
        stopped = self.sim.field(1, "present_position")
        self.assertNotEqual(stopped, start, "the servo did not move while the button was held")
        self.assertGreater(abs(goal - stopped), 200, "the servo ran on to its goal after the tab closed")

    def test_e_2_an_estop_reset_soon_ends_the_held_jog_and_the_page_lets_go(self):
        self.login("op")
        self.sim.command("set 2 41 00")     # no ramp: it stops where it is held
        self.sim.command("set 2 46 2c 01")  # 300 steps/s: the move outlasts the test
        start, goal = self.start_far_move(2)
        button = self.browser.find_element(By.ID, "hold-position")
        ActionChains(self.browser).click_and_hold(button).perform()  # held until released below
        try:
            wait_until(lambda: abs(self.sim.field(2, "present_position") - start) > 20, what="the held jog to move servo 2")
            client = self.modbus()
            self.assertFalse(client.write_coil(1, True, slave=255).isError())
            time.sleep(0.05)  # the scenario: the e-stop reset 50 ms after the latch, the button still held
            self.assertFalse(client.write_coil(1, False, slave=255).isError())
            client.close()
            state = wait_until(lambda: "ended by the e-stop" in self.browser.find_element(By.ID, "jog-state").text and
                               self.browser.find_element(By.ID, "jog-state").text, what="the page to say why the jog ended")
            self.assertIn("ended by the e-stop", self.browser.find_element(By.ID, "message").text)
            self.assertNotIn("active", button.get_attribute("class"), "the page still holds the ended jog: " + state)
            # Still held: the servo stays at the e-stop's hold, never goes on to the goal.
            held = self.sim.field(2, "goal_position")
            self.assertNotEqual(held, goal)
            self.wait_stopped(2)
            self.assertEqual(self.sim.field(2, "goal_position"), held)
        finally:
            ActionChains(self.browser).release().perform()
        # A new press moves again.
        before = self.sim.field(2, "present_position")
        self.hold(2)  # a new press moves again
        self.assertGreater(abs(self.sim.field(2, "present_position") - before), 20, "a new press did not move servo 2")
        self.wait_stopped(2)

    def test_f_a_read_user_cannot_write_or_jog(self):
        self.login("viewer")
        self.open("/servo/2", "#field-acceleration")
        self.assertFalse(self.browser.find_elements(By.CSS_SELECTOR, "#field-acceleration input.edit"))
        self.assertIn("needs operate", self.browser.find_element(By.ID, "field-acceleration").text)
        self.assertFalse(self.browser.find_element(By.ID, "hold-position").is_enabled())
        self.assertFalse(self.browser.find_element(By.ID, "estop").is_enabled())
        before = self.sim.field(2, "acceleration")
        answer = self.fetch("POST", "/api/servo/2/write", {"field": "acceleration", "value": before + 1})
        self.assertEqual(answer["status"], 403, answer)
        answer = self.fetch("POST", "/api/estop", {"latch": True})
        self.assertEqual(answer["status"], 403, answer)
        # The jog message over the page's own WebSocket is refused as well.
        goal_before = self.sim.field(2, "goal_position")
        reply = self.browser.execute_async_script("""
            const done = arguments[0];
            fetch('/api/session').then(r => r.json()).then(s => {
              const ws = new WebSocket('ws://' + location.host + '/ws/servo/2?csrf=' + s.csrf);
              ws.onopen = () => ws.send(JSON.stringify({type: 'jog', mode: 'position', value: 100}));
              ws.onmessage = (e) => { const m = JSON.parse(e.data); if (m.type === 'error') { ws.close(); done(m.message); } };
            });""")
        self.assertIn("operate", reply)
        self.assertEqual(self.sim.field(2, "acceleration"), before)
        self.assertEqual(self.sim.field(2, "goal_position"), goal_before)

    def test_g_estop_latches_and_modbus_writes_get_0x04(self):
        self.login("op")
        self.open("/", "#estop:not([disabled])")
        self.browser.find_element(By.ID, "estop").click()
        wait_until(lambda: "LATCHED" in self.browser.find_element(By.ID, "estop").text, what="the e-stop to latch")
        client = self.modbus()
        answer = client.write_register(42, 2048, slave=1)
        self.assertTrue(answer.isError())
        self.assertEqual(answer.exception_code, 0x04)
        latched = client.read_discrete_inputs(0, 1, slave=255)
        self.assertTrue(latched.bits[0], "unit 255 discrete input 0 (e-stop latched) is not set")
        # Reset needs a confirmation.
        self.browser.find_element(By.ID, "estop").click()
        alert = wait_until(lambda: self._alert(), what="the reset confirmation")
        alert.accept()
        wait_until(lambda: "LATCHED" not in self.browser.find_element(By.ID, "estop").text, what="the e-stop to reset")
        # Written again only after a 0x0B: on a loaded machine the simulated servo may miss its
        # answer's deadline; a 0x04 (still refused) fails at once.
        for attempt in range(3):
            answer = client.write_register(42, 2048, slave=1)
            if not answer.isError() or answer.exception_code != 0x0B:
                break
        self.assertFalse(answer.isError(), f"after the reset the write was answered {answer}")
        client.close()

    def test_h_stale_csrf_and_bad_requests_are_refused(self):
        self.login("eng")
        self.open("/", "#servos-table tr[data-unit]")
        stale = self.browser.execute_script("return fetch('/api/session').then(r => r.json()).then(s => s.csrf)")
        self.login("eng")  # a new login replaces the session and its token
        self.browser.get(self.base + "/")
        answer = self.fetch("POST", "/api/estop", {"latch": True}, csrf=stale)
        self.assertEqual(answer["status"], 403, answer)
        self.assertIn("stale", answer["body"])
        answer = self.fetch("POST", "/api/servo/99/write", {"field": "acceleration", "value": 1})
        self.assertEqual(answer["status"], 404, answer)
        answer = self.fetch("POST", "/api/servo/1/write", {"field": "no_such_field", "value": 1})
        self.assertEqual(answer["status"], 400, answer)

    def test_i_bad_input_gets_a_clear_error_and_modbus_keeps_serving(self):
        import socket
        def exchange(data, read=True):
            with socket.create_connection(("127.0.0.1", self.console_port), timeout=5) as s:
                s.sendall(data)
                if not read:
                    return b""
                reply = b""
                try:
                    while True:
                        chunk = s.recv(65536)
                        if not chunk:
                            break
                        reply += chunk
                except (socket.timeout, ConnectionResetError):
                    pass
                return reply
        self.assertIn(b"400", exchange(b"BREW /pot HTCPCP/1.0\r\n\r\n").split(b"\r\n")[0])
        self.assertIn(b"431", exchange(b"GET / HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 20000 + b"\r\n\r\n").split(b"\r\n")[0])
        big = b"POST /api/login HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n"
        self.assertIn(b"413", exchange(big + b"{" * 100000).split(b"\r\n")[0])
        self.assertIn(b"404", exchange(b"GET /nowhere HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").split(b"\r\n")[0])
        # A WebSocket frame that says it carries 2^62 bytes: the connection is closed, nothing else happens.
        self.login("viewer")
        cookie = self.browser.get_cookie("sms_console")["value"]
        csrf = self.browser.execute_script("return fetch('/api/session').then(r => r.json()).then(s => s.csrf)")
        upgrade = (f"GET /ws/overview?csrf={csrf} HTTP/1.1\r\nHost: 127.0.0.1:{self.console_port}\r\n"
                   f"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                   f"Sec-WebSocket-Version: 13\r\nCookie: sms_console={cookie}\r\n\r\n").encode()
        with socket.create_connection(("127.0.0.1", self.console_port), timeout=5) as s:
            s.sendall(upgrade)
            self.assertIn(b"101", s.recv(4096).split(b"\r\n")[0])
            s.sendall(bytes([0x81, 0xFF]) + (1 << 62).to_bytes(8, "big") + b"\x00\x00\x00\x00" + b"x" * 64)
            s.settimeout(5)
            closed = False
            try:
                while s.recv(65536):
                    pass
                closed = True
            except ConnectionResetError:
                closed = True
            self.assertTrue(closed)
        client = self.modbus()
        answer = client.read_input_registers(56, 2, slave=1)
        self.assertFalse(answer.isError(), answer)
        client.close()

    def test_j_commissioning_scans_a_free_line_and_sets_an_id(self):
        import os
        import subprocess
        self.login("eng")
        self.open("/commission", "#scan:not([disabled])")
        # A line the gateway's bus owns is refused.
        self.browser.find_element(By.ID, "device").send_keys(self.sim.link)
        self.browser.find_element(By.ID, "scan").click()
        wait_until(lambda: "bus `arm`" in self.text("#message"), what="the refusal of the bus's own line")
        device = self.browser.find_element(By.ID, "device")
        device.clear()
        device.send_keys(self.free_line.link)
        self.scan("1000000, 115200", "12", "4,9")
        # The downloadable configuration is one --check-config accepts.
        yaml = self.browser.execute_async_script(
            "fetch('/api/commission/config.yaml').then(r => r.text()).then(arguments[0])")
        path = os.path.join(self.workdir, "scanned.yaml")
        with open(path, "w") as f:
            f.write(yaml)
        check = subprocess.run([os.path.join(self.bin_dir, "sms-gateway"), "--check-config", path],
                               capture_output=True, text=True)
        self.assertEqual(check.returncode, 0, check.stdout + check.stderr + yaml)
        self.assertIn("2 servo(s)", check.stdout)
        # Set ID 9 -> 10; the simulator's own list is the witness.
        self.browser.find_element(By.CSS_SELECTOR, "#found-table tr[data-id='9'] input.new-id").send_keys("10")
        self.browser.find_element(By.CSS_SELECTOR, "#found-table tr[data-id='9'] button.set-id").click()
        wait_until(lambda: self._alert(), what="the confirmation").accept()
        wait_until(lambda: "10:sts" in self.free_line.command("list"), timeout=15, what="servo 9 to answer as 10")
        self.assertNotIn("9:sts", self.free_line.command("list"))

    def test_k_plot_exports_its_window_as_csv_and_the_wheel_and_torque_buttons_drive_the_servo(self):
        import csv
        self.login("op")
        self.open("/servo/1", "#hold-speed:not([disabled])")
        wait_until(lambda: int(self.browser.find_element(By.ID, "plot").get_attribute("data-samples") or 0) > 20,
                   timeout=10, what="20 samples on the plot")
        # Torque off and on: the simulator's torque_enable follows.
        self.browser.find_element(By.ID, "torque-off").click()
        wait_until(lambda: self.sim.field(1, "torque_enable") == 0, what="servo 1's torque to go off")
        self.browser.find_element(By.ID, "torque-on").click()
        wait_until(lambda: self.sim.field(1, "torque_enable") == 1, what="servo 1's torque to come on")
        def hold_to_turn(seconds=None):
            """Held for `seconds`, or until servo 1 turns (as long as a loaded machine takes)."""
            speed = self.browser.find_element(By.ID, "jog-speed")
            speed.clear()
            speed.send_keys("800")
            if seconds is None:
                self.hold(1, button="hold-speed")
                return
            button = self.browser.find_element(By.ID, "hold-speed")
            ActionChains(self.browser).click_and_hold(button).pause(seconds).release().perform()
        # In position mode a speed goal turns nothing: the page says so and nothing is written.
        goal_speed = self.sim.field(1, "goal_speed")
        hold_to_turn(0.3)
        wait_until(lambda: "not in a speed mode" in self.text("#message"), what="the refusal in position mode")
        self.assertEqual(self.sim.field(1, "goal_speed"), goal_speed)
        # Wheel mode: the servo turns while the button is held and stops when it is released.
        self.sim.command("set 1 33 01")  # operating_mode := 1 (wheel) through the simulator's backdoor
        start = self.sim.field(1, "present_position")
        hold_to_turn()
        self.wait_stopped(1)
        self.assertNotEqual(self.sim.field(1, "present_position"), start, "servo 1 did not turn while held")
        self.assertEqual(self.sim.field(1, "goal_speed"), 0, "the release did not stop the wheel")
        # The plotted window as CSV: the samples the plot shows, time rising, the last position the servo's.
        self.browser.find_element(By.ID, "pause").click()
        shown = int(self.browser.find_element(By.ID, "plot").get_attribute("data-samples"))
        self.browser.find_element(By.ID, "csv").click()
        path = os.path.join(self.downloads, "unit1-plot.csv")
        wait_until(lambda: os.path.exists(path) and os.path.getsize(path) > 0, what="the CSV download")
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
        self.assertEqual(rows[0][0], "time_s")
        self.assertIn("present_position [steps]", rows[0])
        self.assertEqual(len(rows) - 1, shown)
        times = [float(r[0]) for r in rows[1:]]
        self.assertEqual(times, sorted(times))
        column = rows[0].index("present_position [steps]")
        last = int(next(r[column] for r in reversed(rows[1:]) if r[column] != ""))
        self.assertLess(abs(last - self.sim.field(1, "present_position")), 5)
        self.browser.find_element(By.ID, "pause").click()
        self.sim.command("set 1 33 00")  # back to position mode for the tests that follow

    def test_l_stopping_a_bus_to_commission_its_line_stops_its_servos_even_a_silent_one(self):
        """A stop combined with faults: servo 2 moving, servo 3 silent when the bus is stopped from the
        commissioning page. The simulator is the witness: servo 2 stops short of its goal, servo 3 gets
        its owed stop the moment the bus runs again; meanwhile PLC writes get 0x04 and the page scans
        the bus's own line."""
        self.sim.command("set 2 41 03")  # slow acceleration (300 steps/s²): the move outlasts the stop, on a loaded machine too
        self.sim.command("set 3 40 01")  # servo 3's torque on, to see its owed stop take it off
        # The page first: a login may take seconds on a loaded machine, the move must not.
        self.login("eng")
        self.open("/commission", "#buses-table tr[data-bus='arm'] button.stop-bus:not([disabled])")
        client = self.modbus()
        start = self.sim.field(2, "present_position")
        goal = 4000 if start < 2048 else 100
        self.write_goal(client, 2, goal)
        self.sim.command("offline 3")  # the fault: servo 3 does not answer its stop
        self.browser.find_element(By.CSS_SELECTOR, "#buses-table tr[data-bus='arm'] button.stop-bus").click()
        wait_until(lambda: self._alert(), what="the stop confirmation").accept()
        wait_until(lambda: "bus arm stopped" in self.text("#message"), timeout=15, what="the bus to stop")
        self.assertIn("1 servo(s) did not answer", self.text("#message"))
        self.wait_stopped(2, timeout=8)  # it brakes at its slow acceleration
        self.assertGreater(abs(goal - self.sim.field(2, "present_position")), 200, "servo 2 ran on to its goal")
        self.assertEqual(self.sim.field(3, "torque_enable"), 1)
        # PLC writes are refused while the line is lent: 0x0A, the path to the servo is gone, as for a
        # bus that is down; the page says why.
        answer = client.write_register(42, 2048, slave=1)
        self.assertTrue(answer.isError())
        self.assertEqual(answer.exception_code, 0x0A)
        wait_until(lambda: "stopped for commissioning" in self.text("#buses-table tr[data-bus='arm'] td.state"),
                   what="the page to show the bus stopped")
        # The bus's own line is free for the page's scan now (its device is filled in).
        self.assertEqual(self.browser.find_element(By.ID, "device").get_attribute("value"), self.sim.link)
        self.scan("1000000", "5", "1,2")  # 3 is silent
        self.screenshot("commissioning.png")
        # Servo 3 answers again; the bus starts and its owed stop reaches it first.
        self.sim.command("online 3")
        self.browser.find_element(By.CSS_SELECTOR, "#buses-table tr[data-bus='arm'] button.start-bus").click()
        wait_until(lambda: "started again" in self.text("#message"), timeout=15, what="the bus to start")
        wait_until(lambda: self.sim.field(3, "torque_enable") == 0, timeout=10, what="servo 3's owed stop")

        def written_again():
            answer = client.write_register(42, 2048, slave=1)
            return not answer.isError()
        wait_until(written_again, timeout=10, what="a PLC write to be accepted again")
        client.close()

    # --- helpers ----------------------------------------------------------------------------------

    def scan(self, bauds, last_id, expected_ids):
        """Scans the commissioning page's line at `bauds` up to `last_id`; expects those IDs found.
        A scan asks each ID once (gateway/tools/tool_scan.cpp), so on a loaded machine an answer
        heard late misses its servo, as it would for an engineer, who scans again: up to three
        scans, each awaited to its end, not a time."""
        self.browser.find_element(By.ID, "bauds").send_keys(bauds)
        self.browser.find_element(By.ID, "last-id").send_keys(last_id)
        found = None
        for _ in range(3):
            self.browser.execute_script("document.getElementById('message').className = ''")
            self.browser.find_element(By.ID, "scan").click()
            wait_until(lambda: self.browser.find_element(By.ID, "message").get_attribute("class") in ("done", "error"),
                       timeout=60, what="the scan to end")
            found = self.browser.execute_script(
                "return [...document.querySelectorAll('#found-table tr[data-id]')].map(r => r.dataset.id).join(',')")
            if found == expected_ids:
                return
        self.assertEqual(found, expected_ids, f"servos found by three scans ({self.text('#message')})")

    def write_goal(self, client, servo, goal):
        """A PLC's goal_position write; a servo timeout (0x0B) on a loaded test machine is retried, as
        a PLC would."""
        for _ in range(3):
            written = client.write_register(42, goal, slave=servo)
            if not written.isError() or getattr(written, "exception_code", 0) != 0x0B:
                break
        self.assertFalse(written.isError(), written)

    def text(self, css):
        return self.browser.execute_script("const e = document.querySelector(arguments[0]); return e ? e.textContent : ''", css)

    def _alert(self):
        try:
            return self.browser.switch_to.alert
        except Exception:  # NoAlertPresentException until it shows
            return None

    def fetch(self, method, path, body, csrf=None):
        """A request from the page itself (same origin, its cookie), with its CSRF token unless given."""
        return self.browser.execute_async_script("""
            const [method, path, body, given, done] = arguments;
            fetch('/api/session').then(r => r.json()).then(s =>
              fetch(path, {method, headers: {'Content-Type': 'application/json', 'X-CSRF-Token': given || s.csrf},
                           body: JSON.stringify(body)}))
              .then(r => r.text().then(t => done({status: r.status, body: t})));""", method, path, body, csrf)


if __name__ == "__main__":
    unittest.main(verbosity=2)
