"""A held jog (hold-to-run) and the safety stops, through the console's own WebSocket API against
the real gateway on sms-sim (docs/CONSOLE.md "Jog panel"). The page keeps holding (heartbeats
going on) while the e-stop is latched over Modbus and reset 20-150 ms later, or while the bus's
watchdog trips and is re-armed as soon: the jog is over for good. The simulator's own state is
the witness that the servo never turns again, the page is told why, and only a new press moves
it again."""
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
TRIP_DELAYS_MS = (20, 80, 150)
# The gateway's own time (its pushes' clock) watched after a stop: over three goal refreshes.
WATCH_US = 800_000
AWAIT_S = 10


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
    # Answers at once, and a generous answer timeout: these tests are about the jog's rule, not
    # wire time (on a loaded machine the servos would otherwise drop offline now and then).
    sim_options = ("--no-timing",)
    bus_yaml = ", response_timeout_ms: 100"

    def setUp(self):
        cookie, csrf = self.api_login("op")
        self.page = ConsoleSocket(self.console_port, f"/ws/servo/{SERVO}", cookie, csrf)
        self.hold = Hold(self.page)
        self.plc = self.modbus()

    def tearDown(self):
        self.hold.stop.set()
        self.page.close()
        self.plc.close()

    # --- the cell ------------------------------------------------------------------------------

    def coil(self, address, value):
        answer = self.plc.write_coil(address, value, slave=255)
        self.assertFalse(answer.isError(), f"gateway unit coil {address} := {int(value)}: {answer}")

    def told_since(self, mark, *types):
        return [m for m in self.page.received()[mark:] if m.get("type") in types]

    def torque_on(self):
        """A set-up write: where a loaded machine held the simulator past the response timeout the
        servo is offline a moment and the gateway answers 0x0B (the product's rule); it is made
        again once the servo answers, at most five times."""
        answer = None
        for _ in range(5):
            mark = len(self.page.received())
            self.page.send({"type": "torque", "on": True})
            answer = wait_until(lambda: self.told_since(mark, "done", "error"), timeout=AWAIT_S,
                                what="the answer to torque on")
            if answer[0] == {"type": "done", "message": "torque on"} or "exception 0x0B" not in answer[0]["message"]:
                break
            wait_until(lambda: self.online(), timeout=AWAIT_S, what="the servo online again")
        self.assertEqual(answer[0], {"type": "done", "message": "torque on"})

    def online(self):
        answer = self.plc.read_discrete_inputs(1008, count=1, slave=SERVO)
        return not answer.isError() and answer.bits[0]

    def wheel_mode(self):
        self.sim.command(f"set {SERVO} 46 00 00")  # goal speed 0 first: wheel mode runs at once
        self.sim.command(f"set {SERVO} 33 01")     # operating_mode 1: wheel (speed)
        self.torque_on()

    def position_mode(self):
        position = self.sim.field(SERVO, "present_position")
        self.sim.command(f"set {SERVO} 42 {position & 0xFF:02x} {position >> 8:02x}")  # goal := here
        self.sim.command(f"set {SERVO} 33 00")     # position mode
        self.sim.command(f"set {SERVO} 41 00")     # no ramp: it stops where it is held
        self.sim.command(f"set {SERVO} 46 2c 01")  # at 300 steps/s: the move outlasts each trial
        self.torque_on()

    def speeds(self):
        return self.sim.field(SERVO, "goal_speed"), self.sim.field(SERVO, "present_speed")

    def press(self, message, moving, what):
        """Presses and holds until `moving()`. A press the gateway could not carry out (it says so:
        the servo did not answer in time on a loaded machine, 0x0B while it is offline) is released
        and made again once the servo answers."""
        last = None
        for _ in range(5):
            mark = len(self.page.received())
            self.hold.press(message)
            result = wait_until(lambda: "moving" if moving() else self.told_since(mark, "error", "jog_ended"),
                                timeout=AWAIT_S, step=0.005, what=what)
            if result == "moving":
                return
            last = result
            self.hold.release()
            wait_until(self.online, timeout=AWAIT_S, what="the servo online again")
        self.fail(f"{what}: five presses failed, the last: {last}")

    def press_speed(self):
        self.press({"type": "jog", "mode": "speed", "value": SPEED},
                   lambda: self.sim.field(SERVO, "goal_speed") == SPEED and self.sim.field(SERVO, "present_speed") != 0,
                   "the held speed jog to turn the servo")

    def release_and_await_still(self):
        self.hold.release()
        wait_until(lambda: self.speeds() == (0, 0), timeout=AWAIT_S, what="the servo to stop after the release")

    # --- a trial ---------------------------------------------------------------------------------

    def watch(self, mark, read, stopped):
        """Calls read() on the simulator from the reset on (message `mark` on) until the servo is
        `stopped` (a watchdog's stop may land after a quick re-arm) and, from then, the gateway's
        clock, as its pushes carry it, has run WATCH_US: the samples."""
        samples = []
        since = {}

        def long_enough():
            samples.append(read())
            if "push" not in since and stopped(samples[-1]):
                since["push"] = len(self.page.received())
            if "push" not in since:
                return False
            pushes = [m for m in self.page.received()[max(mark, since["push"]):] if m.get("type") == "samples"]
            return len(pushes) >= 2 and pushes[-1]["sent_us"] - pushes[0]["sent_us"] >= WATCH_US
        wait_until(long_enough, timeout=20, step=0.01, what="the stop, and the gateway's pushes for 800 ms after it")
        return samples

    def assert_never_turned_again(self, samples, after):
        """(goal speed, present speed) samples from the reset on: once the stop set the servo's
        goal speed to 0, nothing set it turning again."""
        first = next(i for i, sample in enumerate(samples) if sample[0] == 0)
        again = [sample for sample in samples[first:] if sample[0] != 0]
        self.assertFalse(again, f"the servo turned again after {after}: (goal speed, present speed) {again[:5]}")
        self.assertEqual(samples[-1][1], 0, "the servo still turns")

    def told(self, mark, cause):
        """What the page was told since message `mark`: the end of its jog, and why. False when a
        stall of the machine ended the jog (no heartbeat) before the stop: the trial is made again."""
        ended = [m["message"] for m in self.told_since(mark, "jog_ended")]
        self.assertTrue(ended, "the page was not told that its jog ended; it was told: " +
                        str([m for m in self.page.received() if m.get("type") != "samples"][-5:]))
        if ended[0].startswith("no heartbeat"):
            return False
        self.assertTrue(ended[0].startswith(cause), ended)
        wait_until(lambda: [m for m in self.told_since(mark, "samples")
                            if m["jog"] == "stopped" and m["jog_reason"].startswith(cause)],
                   timeout=AWAIT_S, what="the page's jog state to say why it stopped")
        return True

    def trials(self, press, stop, read, stopped, still, cause):
        """Holds a jog, lets `stop()` latch and reset (or trip and re-arm), checks with `still` that
        the servo never moved again while the jog was still held, and that the page was told
        `cause`; then a new press must move it. Made again (at most twice) when inconclusive."""
        for _ in range(3):
            press()
            mark = len(self.page.received())
            stop()
            still(self.watch(len(self.page.received()), read, stopped))
            conclusive = self.told(mark, cause)
            self.hold.release()
            press()  # a new press moves again
            self.hold.release()
            if conclusive:
                return
        self.fail("three trials in a row ended by a missing heartbeat before the stop")


class EstopEndsTheHeldJog(JogStopCase):

    def latch_and_reset(self, delay):
        self.coil(1, True)  # answered once the stop frames are on the wire
        time.sleep(delay / 1000)  # the scenario: the reset this soon after the latch
        self.coil(1, False)

    def test_a_estop_latched_and_reset_soon_ends_a_held_speed_jog(self):
        self.wheel_mode()
        for delay in ESTOP_DELAYS_MS:
            with self.subTest(delay_ms=delay):
                self.trials(self.press_speed, lambda: self.latch_and_reset(delay), self.speeds,
                            lambda sample: sample[0] == 0,
                            lambda samples: self.assert_never_turned_again(samples, f"the e-stop's reset ({delay} ms)"),
                            "ended by the e-stop")
                wait_until(lambda: self.speeds() == (0, 0), timeout=AWAIT_S, what="the servo to stop after the release")
        self.assertFalse(self.plc.read_discrete_inputs(0, 1, slave=255).bits[0], "the e-stop is still latched")

    def test_b_estop_latched_and_reset_soon_ends_a_held_position_jog(self):
        self.position_mode()
        for delay in (20, 75, 150):
            with self.subTest(delay_ms=delay):
                goal = FAR if self.sim.field(SERVO, "present_position") < 2048 else 4095 - FAR

                def press():
                    start = self.sim.field(SERVO, "present_position")
                    self.press({"type": "jog", "mode": "position", "value": goal},
                               lambda: abs(self.sim.field(SERVO, "present_position") - start) > 20,
                               "the held position jog to move the servo")

                def read():
                    return self.sim.field(SERVO, "goal_position"), self.sim.field(SERVO, "present_position")

                def still(samples):
                    # The e-stop's hold made the goal the position it stopped at; it stays so.
                    first = next(i for i, sample in enumerate(samples) if sample[0] != goal)
                    held = samples[first][0]
                    moved = [sample for sample in samples[first:] if sample[0] != held]
                    self.assertFalse(moved, f"the goal moved again after the e-stop's reset ({delay} ms): {moved[:5]}")
                    self.assertLessEqual(abs(samples[-1][1] - held), 10, "the servo did not stay at its hold")

                self.trials(press, lambda: self.latch_and_reset(delay), read, lambda sample: sample[0] != goal, still,
                            "ended by the e-stop")
                wait_until(lambda: self.sim.field(SERVO, "goal_position") != goal, timeout=AWAIT_S,
                           what="the release's hold")

    def test_c_a_press_while_latched_moves_nothing(self):
        self.wheel_mode()
        self.coil(1, True)
        try:
            mark = len(self.page.received())
            self.hold.press({"type": "jog", "mode": "speed", "value": SPEED})
            refusal = wait_until(lambda: self.told_since(mark, "error"), timeout=AWAIT_S,
                                 what="the press to be refused")
            self.assertIn("the e-stop is latched", refusal[0]["message"])
        finally:
            self.coil(1, False)
        # Still held: the reset moves nothing.
        samples = self.watch(len(self.page.received()), lambda: self.sim.field(SERVO, "goal_speed"), lambda s: True)
        self.assertEqual(set(samples), {0}, "the servo turned after the reset without a new press")
        self.hold.release()


class WatchdogTripEndsTheHeldJog(JogStopCase):
    # Fed only by the PLC's heartbeat register, which nobody writes here: a jog's first write
    # starts it counting, and it trips this long after (longer than the worst transaction).
    bus_yaml = JogStopCase.bus_yaml + ", watchdog: {timeout_ms: 1000, feed: heartbeat_register}"

    ARMED, RUNNING, TRIPPED = 1, 2, 3

    def watchdog(self):
        """Bus arm's watchdog state (gateway unit input register 110)."""
        return self.plc.read_input_registers(110, 1, slave=255).registers[0]

    def tripped(self):
        return self.watchdog() == self.TRIPPED

    def armed_and_still(self):
        """The last motion write's count runs out (torque on, the last new press), then the
        watchdog is re-armed: it waits for the next press."""
        wait_until(lambda: self.watchdog() != self.RUNNING, timeout=AWAIT_S, what="the watchdog's count to run out")
        self.coil(2, False)
        self.assertEqual(self.watchdog(), self.ARMED)

    def trip_and_rearm(self, delay):
        wait_until(self.tripped, timeout=AWAIT_S, step=0.005, what="the watchdog to trip")
        time.sleep(delay / 1000)  # the scenario: the re-arm this soon after the trip
        self.coil(2, False)

    def test_a_a_trip_re_armed_soon_ends_a_held_speed_jog(self):
        self.wheel_mode()
        for delay in TRIP_DELAYS_MS:
            with self.subTest(delay_ms=delay):
                self.armed_and_still()
                self.trials(self.press_speed, lambda: self.trip_and_rearm(delay), self.speeds,
                            lambda sample: sample[0] == 0,
                            lambda samples: self.assert_never_turned_again(samples, f"the re-arm ({delay} ms after)"),
                            "ended by the watchdog of bus arm")
                wait_until(lambda: self.sim.field(SERVO, "goal_speed") == 0, timeout=AWAIT_S,
                           what="the release (or the next trip) to stop it")


class TheReleaseStopsWhereTheAxisIs(JogStopCase):
    """The release's stop is the safety layer's hold, with the stop's own ramp: a position jog on the
    gentle ramp a PLC left (acceleration 5, 500 steps/s^2) stands where it was released, instead of
    braking at that ramp past its hold and driving back (docs/SAFETY.md "Stop distance")."""

    def motion(self):
        words = dict(word.split("=", 1) for word in self.sim.command(f"motion {SERVO}").split())
        return words

    def test_a_released_position_jog_on_a_gentle_ramp_stands_where_it_was(self):
        self.position_mode()
        self.sim.command(f"set {SERVO} 41 05")     # acceleration 5: the PLC's gentle ramp
        self.sim.command(f"set {SERVO} 46 e8 03")  # 1000 x 0.732 rpm: as fast as the motor goes
        start = self.sim.field(SERVO, "present_position")
        goal = FAR if start < 2048 else 4095 - FAR
        self.press({"type": "jog", "mode": "position", "value": goal},
                   lambda: abs(self.sim.field(SERVO, "present_position") - start) > 300,
                   "the held position jog to move the servo 300 steps")
        pressed = self.motion()["started_us"]
        self.hold.release()
        stop = wait_until(lambda: (lambda m: m if m["started_us"] != pressed and m["arrived_us"] != "-" and
                                   m["goal"] != str(goal) and m["position"] == m["goal"] else None)(self.motion()),
                          timeout=AWAIT_S, what="the release's hold, and the servo standing at it")
        # The hold goes ahead by what the axis covers while its frame is on the way; where a loaded
        # host held the frame back longer, the servo pulls back what it ran on meanwhile: at most
        # its run-on since the last read it answered (tests/e2e/sim_motion.h), never a ramp's run-on.
        late = abs(int(stop["at_goal_write"]) - int(stop["read_before_goal"]))
        onward = 1 if goal > start else -1
        ran_on = (int(stop["position"]) - int(stop["at_goal_write"])) * onward
        self.assertLessEqual(ran_on, 20, f"the servo ran on from where the release's hold found it: {stop}")
        self.assertLessEqual(-ran_on, 20 + late, f"the servo stood short of where the hold found it: {stop}")
        self.assertLessEqual(int(stop["turned_back"]), 5 + late,
                             f"the servo drove back to the release's hold: {stop}")
        self.assertEqual(self.sim.field(SERVO, "acceleration"), 0, "the hold's stop ramp")


if __name__ == "__main__":
    unittest.main(verbosity=2)
