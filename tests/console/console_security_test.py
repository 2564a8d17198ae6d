"""The console's own defences, end to end against the real gateway on sms-sim (docs/CONSOLE.md
"Access", docs/SECURITY.md "The browser console"): where the login page may send the browser
afterwards (headless Chromium), the pages of things that do not exist, the Content-Security-
Policy of the embedded pages, and the error texts."""
import http.client
import json
import re
import time
import urllib.parse
import urllib.request

from selenium.webdriver.common.by import By

from console_support import LOGIN_TIMEOUT, ConsoleCase, PASSWORD, USERS, free_port, wait_until

METRICS_PORT = free_port()


class ConsoleSecurityTest(ConsoleCase):
    # `spare` is failed on purpose (the per-user backoff); the browser logs in as the others.
    users = {**USERS, "spare": "read"}
    extra_yaml = f"logging: {{metrics_listen: \"127.0.0.1:{METRICS_PORT}\"}}\n"

    # --- after the login: this console's pages only ------------------------------------------------

    def log_out(self):
        # Cookies are deleted for the page's own site: be on the console's first.
        self.browser.get(self.base + "/static/console.css")
        self.browser.delete_all_cookies()

    def login_with_next(self, next_raw):
        """Logs in on /login?next=<next_raw> (put in the URL as it is) and returns the URL the
        browser ends at."""
        self.log_out()
        login_url = self.base + "/login?next=" + next_raw
        self.browser.get(login_url)
        wait_until(lambda: self.browser.find_elements(By.ID, "user"), what="the login form")
        self.browser.find_element(By.ID, "user").send_keys("viewer")
        self.browser.find_element(By.ID, "password").send_keys(PASSWORD)
        self.browser.find_element(By.ID, "submit").click()
        return wait_until(lambda: self.left_login_page(), timeout=LOGIN_TIMEOUT,
                          what=f"the browser to leave {login_url}")

    def left_login_page(self):
        url = self.browser.current_url
        parts = urllib.parse.urlsplit(url)
        if parts.path == "/login" and f"{parts.scheme}://{parts.netloc}" == self.base:
            return None
        return url

    def assert_stays_on_the_console(self, next_raw, expected_path="/"):
        final = self.login_with_next(next_raw)
        parts = urllib.parse.urlsplit(final)
        self.assertEqual(f"{parts.scheme}://{parts.netloc}", self.base,
                         f"next={next_raw!r} sent the browser to another origin: {final}")
        self.assertEqual(parts.path, expected_path, f"next={next_raw!r} ended at {final}")

    def test_next_backslash_escaped(self):
        self.assert_stays_on_the_console("/%5Cevil.example/")

    def test_next_tab_escaped(self):
        self.assert_stays_on_the_console("/%09/evil.example/")

    def test_next_protocol_relative(self):
        self.assert_stays_on_the_console("//evil.example/")

    def test_next_absolute_url(self):
        self.assert_stays_on_the_console("https://evil.example/")

    def test_next_backslash(self):
        self.assert_stays_on_the_console("/\\evil.example/")

    def test_next_javascript(self):
        self.assert_stays_on_the_console("javascript:alert(1)")

    def test_next_encoded_slashes(self):
        self.assert_stays_on_the_console("%2F%2Fevil.example")

    def test_next_dot_segment_before_double_slash(self):
        # Resolves on this origin to the path //evil.example, itself a protocol-relative URL.
        self.assert_stays_on_the_console("/.//evil.example/", expected_path="//evil.example/")

    def test_next_servo_page_is_honoured(self):
        self.assert_stays_on_the_console("/servo/1", expected_path="/servo/1")

    def test_page_asked_for_before_the_login_is_shown_after_it(self):
        self.log_out()
        self.browser.get(self.base + "/servo/2")
        wait_until(lambda: "/login" in self.browser.current_url, what="the redirect to the login page")
        self.assertEqual(urllib.parse.parse_qs(urllib.parse.urlsplit(self.browser.current_url).query)["next"],
                         ["/servo/2"])
        self.browser.find_element(By.ID, "user").send_keys("viewer")
        self.browser.find_element(By.ID, "password").send_keys(PASSWORD)
        self.browser.find_element(By.ID, "submit").click()
        wait_until(lambda: self.browser.current_url == self.base + "/servo/2", timeout=LOGIN_TIMEOUT,
                   what="the servo page after the login")

    # --- pages of things that do not exist -----------------------------------------------------------

    def get(self, path, cookie=None):
        connection = http.client.HTTPConnection("127.0.0.1", self.console_port, timeout=5)
        connection.request("GET", path, headers={"Cookie": cookie} if cookie else {})
        answer = connection.getresponse()
        body = answer.read().decode()
        connection.close()
        return answer, body

    def test_unknown_servo_page_says_so(self):
        self.login("viewer")
        self.browser.get(self.base + "/servo/99")
        message = wait_until(lambda: self.browser.find_element(By.ID, "message").text, what="the page's message")
        self.assertEqual(message, "unit 99 is not a servo unit of this gateway (servo units: 1, 2, 3)")
        cookie, _ = self.api_login("viewer")
        answer, body = self.get("/servo/99", cookie)
        self.assertEqual(answer.status, 404)
        self.assertTrue(answer.getheader("Content-Type").startswith("text/html"), answer.getheader("Content-Type"))
        # A unit that exists still gets its page.
        answer, body = self.get("/servo/1", cookie)
        self.assertEqual(answer.status, 200)
        self.assertIn('src="/static/servo.js"', body)

    def test_unknown_bus_monitor_says_so(self):
        self.login("viewer")
        self.browser.get(self.base + "/bus/nosuch/monitor")
        message = wait_until(lambda: self.browser.find_element(By.ID, "message").text, what="the page's message")
        self.assertEqual(message, "no bus is named nosuch (buses: arm)")

    def test_error_page_escapes_what_it_quotes(self):
        cookie, _ = self.api_login("viewer")
        answer, body = self.get("/bus/%3Cb%3Ex%3C%2Fb%3E/monitor", cookie)
        self.assertEqual(answer.status, 404)
        self.assertIn("no bus is named &lt;b&gt;x&lt;/b&gt; (buses: arm)", body)
        self.assertNotIn("<b>x</b>", body)

    # --- the Content-Security-Policy and the pages ------------------------------------------------------

    def test_monitor_page_is_styled_within_the_content_security_policy(self):
        self.login("viewer")
        self.open("/bus/arm/monitor", "#frames tbody")
        # 70 px comes from console.css; an inline style would be blocked (the input would be wider).
        self.assertEqual(self.browser.execute_script(
            "return getComputedStyle(document.getElementById('servo')).width"), "70px")
        for page in ("overview.html", "servo.html", "commission.html", "monitor.html", "login.html"):
            answer, body = self.get("/static/" + page)
            self.assertEqual(answer.status, 200, page)
            self.assertNotIn("style=", body, f"{page} has an inline style, which the console's CSP blocks")
            self.assertNotIn("<style", body, f"{page} has an inline style, which the console's CSP blocks")
        self.assertNotIn("unsafe-inline", answer.getheader("Content-Security-Policy"))

    def test_error_texts_show_slashes(self):
        answer, body = self.get("/static/nosuch/deeper.js")
        self.assertEqual(answer.status, 404)
        self.assertEqual(json.loads(body)["error"], "no page /static/nosuch/deeper.js here; the overview is at /")
        answer, body = self.get("/static/nosuch.js")
        self.assertEqual(json.loads(body)["error"], "no file nosuch.js here")

    # --- failed logins: the backoff per source address and per user --------------------------------
    # From other loopback addresses than the browser's 127.0.0.1, which must not be held up.

    def login_from(self, source, user, password):
        connection = http.client.HTTPConnection("127.0.0.1", self.console_port, timeout=LOGIN_TIMEOUT,
                                                source_address=(source, 0))
        connection.request("POST", "/api/login", json.dumps({"user": user, "password": password}),
                           {"Content-Type": "application/json"})
        answer = connection.getresponse()
        body = json.loads(answer.read())
        connection.close()
        return answer, body

    def fail_into_a_long_wait(self, fail):
        """Five failures (fail(1) .. fail(5)) make the next login wait 1 s, each further one twice
        as long: two more, each after the wait before it, make a 4 s wait, which the next login
        falls inside on a loaded machine too."""
        for attempt in range(1, 6):
            fail(attempt)
        for attempt, wait in ((6, 1), (7, 2)):
            time.sleep(wait + 0.2)
            fail(attempt)

    def assert_waits(self, answer, body, why):
        self.assertEqual(answer.status, 429, body)
        retry = int(answer.getheader("Retry-After"))
        self.assertGreaterEqual(retry, 1)
        self.assertEqual(body["retry_after_s"], retry)
        self.assertEqual(body["error"], f"{why}: try again in {retry} s")
        return retry

    def metric(self, sample):
        text = urllib.request.urlopen(f"http://127.0.0.1:{METRICS_PORT}/metrics", timeout=5).read().decode()
        found = re.search("^" + re.escape(sample) + r" (\d+)$", text, re.MULTILINE)
        self.assertIsNotNone(found, f"{sample} is not in /metrics")
        return int(found.group(1))

    def test_throttle_per_address(self):
        failed_before = self.metric('sms_gateway_console_logins_total{result="failed"}')
        throttled_before = self.metric('sms_gateway_console_logins_total{result="throttled"}')
        def fail(attempt):  # the first five failures cost nothing but the answer
            answer, body = self.login_from("127.0.0.2", f"nobody{attempt}", "wrong")
            self.assertEqual(answer.status, 401, f"attempt {attempt}: {body}")
            self.assertEqual(body["error"], "unknown user or wrong password")
        self.fail_into_a_long_wait(fail)
        # Then the address waits, even with a right password, and is told how long.
        answer, body = self.login_from("127.0.0.2", "viewer", PASSWORD)
        retry = self.assert_waits(answer, body, "too many failed logins from 127.0.0.2")
        self.assertGreaterEqual(self.metric('sms_gateway_console_login_waits{scope="address"}'), 1)
        # Another address is not held up.
        answer, body = self.login_from("127.0.0.3", "viewer", PASSWORD)
        self.assertEqual(answer.status, 200, body)
        # Once the wait is over, the right password logs in from there.
        wait_until(lambda: self.login_from("127.0.0.2", "viewer", PASSWORD)[0].status == 200, timeout=retry + 10,
                   step=0.25, what="the address's wait to end")
        self.assertGreaterEqual(self.metric('sms_gateway_console_logins_total{result="failed"}'), failed_before + 5)
        self.assertGreaterEqual(self.metric('sms_gateway_console_logins_total{result="throttled"}'),
                                throttled_before + 1)

    def test_throttle_per_user(self):
        def fail(i):  # failures in spare's name, each from another address
            answer, body = self.login_from(f"127.0.1.{i}", "spare", "wrong")
            self.assertEqual(answer.status, 401, body)
        self.fail_into_a_long_wait(fail)
        answer, body = self.login_from("127.0.1.9", "spare", PASSWORD)
        retry = self.assert_waits(answer, body, "too many failed logins for user `spare`")
        # The other users are not held up, from the same address either.
        answer, body = self.login_from("127.0.1.9", "viewer", PASSWORD)
        self.assertEqual(answer.status, 200, body)
        # After the wait the right password logs in, which clears spare's count: four failures
        # later a login is still checked at once.
        wait_until(lambda: self.login_from("127.0.1.10", "spare", PASSWORD)[0].status == 200, timeout=retry + 10,
                   step=0.25, what="spare's wait to end")
        for i in range(1, 5):
            answer, body = self.login_from(f"127.0.2.{i}", "spare", "wrong")
            self.assertEqual(answer.status, 401, body)
        answer, body = self.login_from("127.0.2.9", "spare", PASSWORD)
        self.assertEqual(answer.status, 200, body)


if __name__ == "__main__":
    import unittest
    unittest.main()
