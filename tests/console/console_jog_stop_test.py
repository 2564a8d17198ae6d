"""A held jog (hold-to-run) and the safety stops, through the console's own WebSocket API against
the real gateway on sms-sim (docs/CONSOLE.md "Jog panel"). The page keeps holding (heartbeats going on)
while the e-stop is latched over Modbus and reset 20-150 ms later, or while the bus's watchdog
trips and is re-armed as soon: the jog is over for good. The simulator's own state is the witness
that the servo never turns again, the page is told why, and only a new press moves it again."""
import threading
import time
import unittest

from console_support import ConsoleSocket, GatewayCase, wait_until

SERVO = 1
SPEED = 600        # a wheel-mode jog
FAR = 3900         # a position jog's goal, far from the middle
# A stop lasting this long (ms) is shorter than two of the jog's goal refreshes (250 ms): it
# fell between them, unseen, before the fix.
ESTOP_DELAYS_MS = (20, 30, 40, 55, 70, 85, 100, 110, 120, 130, 140, 150)
# The gateway's own time (its pushes' clock) watched after a reset: over three goal refreshes.
WATCH_US = 800_000


class Hold:
    """A page holding a jog button: the press, then a heartbeat every 20 ms until released. It
    keeps holding whatever the gateway says (a page that takes no notice)."""

    def __init__(self, socket):
        self.socket = socket
        self.stop = threading.Event()
        self.thread = None

    def press(self, message):
        self.stop.clear()
        self.socket.send(message)
        self.thread = threading.Thread(target=self._beat, daemon=True)
        self.thread.start()

    def _beat(self):
        while not self.stop.wait(0.02):
            self.socket.send({"type": "heartbeat"})

    def release(self):
        self.stop.set()
        if self.thread:
            self.thread.join(5)
        self.socket.send({"type": "release"})


class JogStopCase(GatewayCase):
    servo_ids = "1-2"

    def setUp(self):
        cookie, csrf = self.api_login("op")
        self.page = ConsoleSocket(self.console_port, f"/ws/servo/{SERVO}", cookie, csrf)
        self.hold = Hold(self.page)
        self.plc = self.modbus()

    def tearDown(self):
        self.hold.stop.set()
        self.page.close()
        self.plc.close()

    def coil(self, address, value):
        answer = self.plc.write_coil(address, value, slave=255)
        self.assertFalse(answer.isError(), f"gateway unit coil {address} := {int(value)}: {answer}")

    def torque_on(self):
        self.page.send({"type": "torque", "on": True})
        wait_until(lambda: self.sim.field(SERVO, "torque_enable") == 1, what="torque on")

    def wheel_mode(self):
        self.sim.command(f"set {SERVO} 46 00 00")  # goal speed 0 first: wheel mode runs at once
        self.sim.command(f"set {SERVO} 33 01")     # operating_mode 1: wheel (speed)
        self.torque_on()

    def press_speed(self):
        self.hold.press({"type": "jog", "mode": "speed", "value": SPEED})
        wait_until(lambda: self.sim.field(SERVO, "goal_speed") == SPEED and self.sim.field(SERVO, "present_speed") != 0,
                   step=0.005, what="the held speed jog to turn the servo")

    def release_and_await_still(self):
        self.hold.release()
        wait_until(lambda: self.sim.field(SERVO, "goal_speed") == 0 and self.sim.field(SERVO, "present_speed") == 0,
                   what="the servo to stop after the release")

    def watch_after_reset(self, mark, read):
        """Calls read() on the simulator until the gateway's clock, as its pushes carry it, has run
        WATCH_US past the first push that came after the reset (message `mark` on): the samples."""
        samples = []

        def long_enough():
            samples.append(read())
            pushes = [m for m in self.page.received()[mark:] if m.get("type") == "samples"]
            return len(pushes) >= 2 and pushes[-1]["sent_us"] - pushes[0]["sent_us"] >= WATCH_US
        wait_until(long_enough, timeout=20, step=0.01, what="the gateway's pushes for 800 ms after the reset")
        return samples

    def told(self, mark, cause):
        """What the page was told since message `mark`: the end of its jog, and why."""
        ended = [m["message"] for m in self.page.received()[mark:] if m.get("type") == "jog_ended"]
        self.assertTrue(ended, "the page was not told that its jog ended; it was told: " +
                        str([m for m in self.page.received() if m.get("type") != "samples"][-5:]))
        if ended[0].startswith("no heartbeat"):
            return False  # the machine stalled the page before the stop: the trial proves nothing more
        self.assertTrue(ended[0].startswith(cause), ended)
        state = wait_until(lambda: [m for m in self.page.received()[mark:] if m.get("type") == "samples"
                                    and m["jog"] == "stopped" and m["jog_reason"].startswith(cause)],
                           what="the page's jog state to say why it stopped")
        self.assertTrue(state)
        return True

    def trial(self, stop, cause, press, read, still):
        """Holds a jog, lets `stop()` latch and reset (or trip and re-arm), and checks with `still` that the servo
        never moved again; then a new press must move it. True when the trial was conclusive."""
        press()
        mark = len(self.page.received())
        stop()
        after = len(self.page.received())
        samples = self.watch_after_reset(after, read)
        still(samples)
        conclusive = self.told(mark, cause)
        self.hold.release()
        # A new press moves again.
        press()
        return conclusive


class EstopEndsTheHeldJog(JogStopCase):

    def test_a_estop_latched_and_reset_soon_ends_a_held_speed_jog(self):
        self.wheel_mode()
        client = self.plc
        for delay in ESTOP_DELAYS_MS:
            with self.subTest(delay_ms=delay):
                def stop():
                    self.coil(1, True)
                    time.sleep(delay / 1000)  # the scenario: a reset this soon after the latch
                    self.coil(1, False)

                def still(samples):
                    turning = [s for s in samples if s[0] != 0]
                    self.assertFalse(turning, f"the servo turned again after the e-stop's reset ({delay} ms): "
                                              f"(goal speed, present speed) {turning[:5]}")
                    self.assertEqual(samples[-1][1], 0, "the servo still turns")

                for _ in range(3):  # a trial the machine's load made inconclusive is made again
                    if self.trial(stop, "ended by the e-stop", self.press_speed,
                                  lambda: (self.sim.field(SERVO, "goal_speed"), self.sim.field(SERVO, "present_speed")),
                                  still):
                        break
                    self.release_and_await_still()
                self.release_and_await_still()
        self.assertFalse(client.read_discrete_inputs(0, 1, slave=255).bits[0], "the e-stop is still latched")

    def test_b_estop_latched_and_reset_soon_ends_a_held_position_jog(self):
        position = self.sim.field(SERVO, "present_position")
        self.sim.command(f"set {SERVO} 42 {position & 0xFF:02x} {position >> 8:02x}")  # goal := here
        self.sim.command(f"set {SERVO} 33 00")     # position mode
        self.sim.command(f"set {SERVO} 41 00")     # no ramp: it stops where it is held
        self.sim.command(f"set {SERVO} 46 2c 01")  # at 300 steps/s: the move outlasts each trial
        self.torque_on()
        for delay in (20, 75, 150):
            with self.subTest(delay_ms=delay):
                goal = FAR if self.sim.field(SERVO, "present_position") < 2048 else 4095 - FAR
                held = {}

                def press():
                    start = self.sim.field(SERVO, "present_position")
                    self.hold.press({"type": "jog", "mode": "position", "value": goal})
                    wait_until(lambda: abs(self.sim.field(SERVO, "present_position") - start) > 20, step=0.005,
                               what="the held position jog to move the servo")

                def stop():
                    self.coil(1, True)
                    time.sleep(delay / 1000)
                    self.coil(1, False)

                def read():
                    return self.sim.field(SERVO, "goal_position"), self.sim.field(SERVO, "present_position")

                def still(samples):
                    # The e-stop's hold made the goal the position it stopped at; it stays so.
                    held["goal"] = samples[0][0]
                    self.assertNotEqual(held["goal"], goal, "the e-stop did not hold the servo")
                    moved = [s for s in samples if s[0] != held["goal"]]
                    self.assertFalse(moved, f"the goal moved again after the e-stop's reset ({delay} ms): {moved[:5]}")
                    self.assertLessEqual(abs(samples[-1][1] - held["goal"]), 10, "the servo did not stay at its hold")

                for _ in range(3):
                    if self.trial(stop, "ended by the e-stop", press, read, still):
                        break
                    self.hold.release()
                self.hold.release()
                wait_until(lambda: self.sim.field(SERVO, "goal_position") != goal, what="the release's hold")

    def test_c_a_press_while_latched_moves_nothing(self):
        self.wheel_mode()
        self.coil(1, True)
        try:
            mark = len(self.page.received())
            self.hold.press({"type": "jog", "mode": "speed", "value": SPEED})
            refusal = wait_until(lambda: [m for m in self.page.received()[mark:] if m.get("type") == "error"],
                                 what="the press to be refused")
            self.assertIn("the e-stop is latched", refusal[0]["message"])
        finally:
            self.coil(1, False)
        # Still held: the reset moves nothing.
        mark = len(self.page.received())
        samples = self.watch_after_reset(mark, lambda: self.sim.field(SERVO, "goal_speed"))
        self.assertEqual(set(samples), {0}, "the servo turned after the reset without a new press")
        self.hold.release()


class WatchdogTripEndsTheHeldJog(JogStopCase):
    # Fed only by the PLC's heartbeat register, which nobody writes here: a jog's first write
    # starts it counting, and it trips this long after.
    bus_yaml = ", watchdog: {timeout_ms: 500, feed: heartbeat_register}"

    def tripped(self):
        return self.plc.read_discrete_inputs(1, 1, slave=255).bits[0]

    def test_a_a_trip_re_armed_soon_ends_a_held_speed_jog(self):
        self.wheel_mode()
        for delay in (20, 80, 150):
            with self.subTest(delay_ms=delay):
                self.coil(2, False)
                wait_until(lambda: not self.tripped(), what="the watchdog re-armed")

                def stop():
                    wait_until(self.tripped, step=0.005, what="the watchdog to trip")
                    time.sleep(delay / 1000)  # the scenario: a re-arm this soon after the trip
                    self.coil(2, False)

                def still(samples):
                    turning = [s for s in samples if s[0] != 0]
                    self.assertFalse(turning, f"the servo turned again after the re-arm ({delay} ms): {turning[:5]}")

                for _ in range(3):
                    if self.trial(stop, "ended by the watchdog of bus arm", self.press_speed,
                                  lambda: (self.sim.field(SERVO, "goal_speed"), self.sim.field(SERVO, "present_speed")),
                                  still):
                        break
                    self.hold.release()
                self.hold.release()
                wait_until(lambda: self.sim.field(SERVO, "goal_speed") == 0, what="the release (or the next trip) to stop it")


if __name__ == "__main__":
    unittest.main(verbosity=2)
