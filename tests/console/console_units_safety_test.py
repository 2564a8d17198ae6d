"""The console speaks the cell's units and shows the safety state where the user acts: real pages
in headless Chromium against the real gateway on sms-sim (docs/CONSOLE.md "Units", "The safety
panel"). Bus arm has a 1000 ms any_write watchdog. Witnesses: the simulator's own fields, scaled
by the table's unit, and its state after a trip."""
import unittest

from selenium.webdriver.common.by import By

from console_support import ConsoleCase, wait_until


def le16(value):
    """A 2-byte field as the simulator's `set` backdoor takes it (low byte first)."""
    return f"{value & 0xFF:02X} {value >> 8:02X}"


class UnitsAndSafetyTest(ConsoleCase):
    bus_yaml = ConsoleCase.bus_yaml + ", retries: 1, watchdog: {timeout_ms: 1000, feed: any_write}"

    def text(self, css):
        return self.browser.execute_script(
            "const e = document.querySelector(arguments[0]); return e ? e.textContent : ''", css)

    def attribute(self, css, name):
        return self.browser.find_element(By.CSS_SELECTOR, css).get_attribute(name)

    def _alert(self):
        try:
            return self.browser.switch_to.alert
        except Exception:  # NoAlertPresentException until it shows
            return None

    def write_field(self, name, value):
        box = self.browser.find_element(By.CSS_SELECTOR, f"#field-{name} input.edit")
        box.clear()
        box.send_keys(str(value))
        self.browser.find_element(By.CSS_SELECTOR, f"#field-{name} button.write").click()

    def test_a_overview_and_servo_page_show_scaled_values_with_units(self):
        self.login("viewer")
        self.open("/", "#servos-table tr[data-unit='1'] td.voltage[data-raw]:not([data-raw=''])")
        # The simulator's raw fields, scaled as the sts table says: 0.1 V, °C, 0.1 %.
        def overview_matches():
            volts = self.sim.field(1, "present_voltage")
            celsius = self.sim.field(1, "present_temperature")
            return (self.text("#servos-table tr[data-unit='1'] td.voltage") == f"{volts / 10:.1f} V"
                    and self.text("#servos-table tr[data-unit='1'] td.temperature") == f"{celsius} °C")
        wait_until(overview_matches, what="servo 1's voltage and temperature in V and °C on the overview")
        self.assertRegex(self.text("#servos-table tr[data-unit='1'] td.load"), r"^-?\d+\.\d %$")
        self.assertRegex(self.text("#servos-table tr[data-unit='1'] td.position"), r"^-?\d+ steps$")

        self.open("/servo/1", "#field-present_voltage td.raw:not(:empty)")
        def servo_page_matches():
            volts = self.sim.field(1, "present_voltage")
            return (self.text("#field-present_voltage td.value") == f"{volts / 10:.1f} V"
                    and self.text("#field-present_voltage td.raw") == str(volts))
        wait_until(servo_page_matches, what="present_voltage as V with its raw value on the servo page")
        self.assertIn("V", self.text("#field-present_voltage"))
        self.assertRegex(self.text("#field-present_current td.value"), r"^-?\d+\.\d mA$")
        # The plot's axis says the unit of what it shows; the legend each field's.
        wait_until(lambda: self.attribute("#plot", "data-axis") == "steps", what="the axis in steps")
        self.browser.find_element(By.ID, "plot-present_voltage").click()
        wait_until(lambda: self.attribute("#plot", "data-axis") == "steps, V", what="the axis in steps and V")
        self.assertIn("present_voltage [V]", self.text("#plot-fields"))
        self.screenshot("servo-units.png")

    def test_b_the_jog_slider_spans_the_angle_limits_and_starts_at_the_present_position(self):
        self.login("op")
        self.open("/servo/1", "#hold-position:not([disabled])")
        wait_until(lambda: self.attribute("#jog-position-range", "max") == "4095", timeout=10,
                   what="the slider to end at the angle limit 4095")
        self.assertEqual(self.attribute("#jog-position-range", "min"), "0")
        present = self.sim.field(1, "present_position")
        self.assertLess(abs(int(self.attribute("#jog-position", "value")) - present), 5)
        self.assertEqual(self.attribute("#jog-position-range", "value"), self.attribute("#jog-position", "value"))
        # Servo 2 with narrower limits (written through the simulator's backdoor): its page's slider.
        self.sim.command(f"set 2 9 {le16(100)}")
        self.sim.command(f"set 2 11 {le16(3000)}")
        self.open("/servo/2", "#hold-position:not([disabled])")
        wait_until(lambda: (self.attribute("#jog-position-range", "min"), self.attribute("#jog-position-range", "max"))
                   == ("100", "3000"), timeout=10, what="servo 2's slider to span 100..3000")
        self.assertIn("angle limits", self.text("#jog-range"))

    def test_c_a_watchdog_trip_shows_in_the_panel_and_names_itself_in_a_refusal(self):
        self.login("op")
        self.open("/servo/3", "#field-goal_position input.edit")
        wait_until(lambda: "armed" in self.text("#safety tr[data-bus='arm'] td.wd-state"), what="the watchdog armed")
        self.assertIn("any carried-out write", self.text("#safety tr[data-bus='arm'] td.wd-feed"))
        # A slow move (the simulator's goal speed, set through its backdoor), cut short by the trip.
        self.sim.command(f"set 3 46 {le16(5)}")  # 5 × 0.732 rpm: about 250 steps/s
        start = self.sim.field(3, "present_position")
        goal = 4000 if start < 2000 else 100
        self.write_field("goal_position", goal)
        wait_until(lambda: "tripped" in self.text("#safety tr[data-bus='arm'] td.wd-state"), timeout=5,
                   what="the panel to show the watchdog tripped")
        self.assertIn("no feed for 1000 ms", self.text("#safety tr[data-bus='arm'] td.wd-state"))
        wait_until(lambda: "last stop: watchdog" in self.text("#safety tr[data-bus='arm'] td.wd-cause"),
                   what="the last stop's cause")
        self.assertIn("watchdog of bus arm tripped", self.text("#safety tr[data-bus='arm'] td.motion"))
        note = wait_until(lambda: self.text("#move-stopped"), timeout=10,
                          what="the page to say the trip stopped its move")
        self.assertRegex(note, r"goal_position := \d+: stopped by the watchdog of bus arm at \d\d:\d\d:\d\d"
                               r".*short of its goal")
        self.assertNotEqual(self.sim.field(3, "present_position"), goal)
        self.browser.execute_script("window.scrollTo(0, 0)")
        self.screenshot("safety-tripped.png")
        # An edit now: the refusal names the rule.
        self.write_field("goal_position", 2048)
        message = wait_until(lambda: "refused: bus" in self.text("#message") and self.text("#message"),
                             what="the refusal")
        self.assertIn("refused: bus arm: its watchdog tripped", message)
        self.assertNotIn("e-stop is latched", message)
        # Re-arm from the panel (operate): armed again, nothing moved.
        self.browser.find_element(By.CSS_SELECTOR, "#safety tr[data-bus='arm'] button.rearm").click()
        wait_until(lambda: self.text("#safety tr[data-bus='arm'] td.wd-state").startswith("armed"),
                   what="the watchdog re-armed")
        self.sim.command(f"set 3 46 {le16(0)}")

    def test_d_an_estop_latches_in_the_panel_names_itself_and_resets_for_operate_only(self):
        self.login("op")
        self.open("/servo/2", "#field-goal_position input.edit")
        # The safety panel is built at the first push of the safety facts, after the page.
        wait_until(lambda: self.text("#estop-state") == "released", what="the safety panel's first facts")
        reset = self.browser.find_element(By.ID, "estop-reset")
        self.assertFalse(reset.is_enabled(), "reset offered while the e-stop is released")
        self.browser.find_element(By.ID, "estop").click()
        wait_until(lambda: self.text("#estop-state") == "LATCHED", what="the panel to show the e-stop latched")
        self.assertIn("refused: e-stop latched", self.text("#safety tr[data-bus='arm'] td.motion"))
        self.write_field("goal_position", 2000)
        # The write's own answer (the e-stop button's message also says "refused").
        message = wait_until(lambda: "refused: bus" in self.text("#message") and self.text("#message"),
                             what="the write's refusal")
        self.assertIn("refused: bus arm: the e-stop is latched", message)
        # A read user sees the latch and gets no reset.
        self.login("viewer")
        self.open("/", "#estop-state")
        wait_until(lambda: self.text("#estop-state") == "LATCHED", what="the viewer's panel to show the latch")
        self.assertFalse(self.browser.find_element(By.ID, "estop-reset").is_enabled())
        self.assertIn("operate", self.attribute("#estop-reset", "title"))
        # The operate user resets it from the panel, after a confirmation.
        self.login("op")
        self.open("/servo/2", "#estop-reset:not([disabled])")
        self.browser.find_element(By.ID, "estop-reset").click()
        wait_until(lambda: self._alert(), what="the reset confirmation").accept()
        wait_until(lambda: self.text("#estop-state") == "released", what="the e-stop to be released")
        self.assertEqual(self.text("#safety tr[data-bus='arm'] td.motion"), "allowed")

    def test_e_the_overviews_tag_lists_are_what_sms_gateway_tags_writes(self):
        import json
        import os
        import subprocess
        self.login("viewer")
        self.open("/", "#tag-lists a")
        links = [a.get_attribute("href") for a in self.browser.find_elements(By.CSS_SELECTOR, "#tag-lists a")]
        self.assertEqual([link.rsplit("/", 1)[1] for link in links], ["tags.csv", "node-red.json", "fuxa.json"])
        fetch = "fetch(arguments[0]).then(r => r.text()).then(arguments[1])"
        csv = self.browser.execute_async_script(fetch, "/api/tags/tags.csv")
        # Bytes, not text: the CSV's CRLF line ends (RFC 4180) are part of what is compared.
        tool = subprocess.run([os.path.join(self.bin_dir, "sms-gateway"), "tags", "--config", self.config_path,
                               "--format", "csv"], capture_output=True)
        self.assertEqual(tool.returncode, 0, tool.stderr)
        self.assertEqual(csv, tool.stdout.decode("utf-8"))
        self.assertIn("present_voltage", csv)
        flow = json.loads(self.browser.execute_async_script(fetch, "/api/tags/node-red.json"))
        self.assertTrue(any(node.get("type") == "modbus-read" and node.get("showErrors") for node in flow))
        devices = json.loads(self.browser.execute_async_script(fetch, "/api/tags/fuxa.json"))
        self.assertTrue(devices)
        missing = self.browser.execute_async_script(
            "fetch(arguments[0]).then(r => r.json().then(j => [r.status, j.error])).then(arguments[1])",
            "/api/tags/nosuch.txt")
        self.assertEqual(missing[0], 404)
        self.assertIn("tags.csv", missing[1])


if __name__ == "__main__":
    unittest.main(verbosity=2)
