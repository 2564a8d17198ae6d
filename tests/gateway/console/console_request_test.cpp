#include "gateway/console/console_request.h"

#include <gtest/gtest.h>

namespace sms::gateway::console {
namespace {

TEST(ConsoleRequest, PathsMatchPatternsWithNamedSegments) {
  PathParams params;
  EXPECT_TRUE(match_path("/servo/{unit}", "/servo/3", params));
  EXPECT_EQ(params.get("unit"), "3");
  PathParams bus;
  EXPECT_TRUE(match_path("/bus/{name}/monitor", "/bus/left%20arm/monitor", bus));
  EXPECT_EQ(bus.get("name"), "left arm");
  PathParams none;
  EXPECT_FALSE(match_path("/servo/{unit}", "/servo/", none));
  EXPECT_FALSE(match_path("/servo/{unit}", "/servo/3/x", none));
  EXPECT_FALSE(match_path("/servo/{unit}", "/servo/%zz", none));
  EXPECT_FALSE(match_path("/", "", none));
  EXPECT_TRUE(match_path("/", "/", none));
  EXPECT_FALSE(match_path("/", "//", none));
  EXPECT_EQ(path_of("/ws/servo/1?csrf=x"), "/ws/servo/1");
}

TEST(ConsoleRequest, QueryAndCookieValues) {
  EXPECT_EQ(query_value("/ws?a=1&csrf=ab%2Bc&b", "csrf"), "ab+c");
  EXPECT_EQ(query_value("/ws?b", "b"), "");
  EXPECT_FALSE(query_value("/ws", "csrf"));
  EXPECT_FALSE(query_value("/ws?csrf=%0", "csrf"));
  EXPECT_EQ(cookie_value("x=1; sms_console=tok; y=2", "sms_console"), "tok");
  EXPECT_FALSE(cookie_value("sms_consolex=1", "sms_console"));
  EXPECT_FALSE(percent_decode("a%00b"));
}

// The login redirect's `next`: a whole target, its query too, one value that decodes back.
TEST(ConsoleRequest, APercentEncodedTargetDecodesBackWhole) {
  const std::string target = "/bus/arm/monitor?servo=3&kind=write answer";
  const std::string encoded = percent_encode(target);
  EXPECT_EQ(encoded, "/bus/arm/monitor%3Fservo%3D3%26kind%3Dwrite%20answer");
  EXPECT_EQ(query_value("/login?next=" + encoded, "next"), target);
}

TEST(ConsoleRequest, UnitsAreOneTo255InDecimal) {
  EXPECT_EQ(parse_unit("1"), 1);
  EXPECT_EQ(parse_unit("255"), 255);
  EXPECT_FALSE(parse_unit("0"));
  EXPECT_FALSE(parse_unit("256"));
  EXPECT_FALSE(parse_unit("0x1"));
  EXPECT_FALSE(parse_unit("-1"));
  EXPECT_FALSE(parse_unit(""));
  EXPECT_FALSE(parse_unit("0001"));
}

TEST(ConsoleRequest, BodiesSayWhatIsWrong) {
  const auto write = parse_field_write(R"({"field":"goal_position","value":2048})");
  ASSERT_TRUE(write);
  EXPECT_EQ(write->field, "goal_position");
  EXPECT_EQ(write->value, 2048);
  EXPECT_EQ(parse_field_write(R"({"field":"goal_position","value":2048.0})")->value, 2048);
  EXPECT_EQ(parse_field_write("not json").error(), "the body is not JSON");
  EXPECT_EQ(parse_field_write("[1]").error(), "the body must be a JSON object");
  EXPECT_EQ(parse_field_write(R"({"field":"x","value":1.5})").error(), "`value` must be an integer");
  EXPECT_EQ(parse_field_write(R"({"value":1})").error(), "`field` (a string) is missing");
  EXPECT_TRUE(parse_estop(R"({"latch":false})"));
  EXPECT_FALSE(parse_estop(R"({"latch":"yes"})"));
  EXPECT_FALSE(parse_login(R"({"user":"a"})"));
}

TEST(ConsoleRequest, JogMessages) {
  using Kind = JogMessage::Kind;
  EXPECT_EQ(parse_jog_message(R"({"type":"heartbeat"})")->kind, Kind::Heartbeat);
  EXPECT_EQ(parse_jog_message(R"({"type":"release"})")->kind, Kind::Release);
  const auto jog = parse_jog_message(R"({"type":"jog","mode":"speed","value":-300})");
  ASSERT_TRUE(jog);
  EXPECT_EQ(jog->kind, Kind::JogSpeed);
  EXPECT_EQ(jog->value, -300);
  EXPECT_TRUE(parse_jog_message(R"({"type":"torque","on":true})")->on);
  EXPECT_FALSE(parse_jog_message(R"({"type":"jog","mode":"fly","value":1})"));
  EXPECT_EQ(parse_jog_message(R"({"type":"dance"})").error(),
            "unknown message type dance (heartbeat, jog, release, torque)");
}

TEST(ConsoleRequest, PrintableKeepsPrintableAsciiAndHidesControlCharacters) {
  // A path reads as it was asked for (it used to come out as "?static?...").
  EXPECT_EQ(printable("/static/nosuch.js"), "/static/nosuch.js");
  EXPECT_EQ(printable("a\"b'c <x> & {y} ~ `z` | 100%"), "a\"b'c <x> & {y} ~ `z` | 100%");
  // A forged log line, a NUL, DEL and bytes past ASCII (UTF-8 é) do not get through.
  EXPECT_EQ(printable("alice\nconsole: user `root` logged in"), "alice?console: user `root` logged in");
  EXPECT_EQ(printable(std::string_view("a\0b\r\t\x7f", 6)), "a?b???");
  EXPECT_EQ(printable("caf\xc3\xa9"), "caf??");
  EXPECT_EQ(printable(std::string(100, '/'), 4), "////...");
}

TEST(ConsoleRequest, HtmlEscapeEscapesMarkup) {
  EXPECT_EQ(html_escape("<script>alert('x') & \"y\"</script>"),
            "&lt;script&gt;alert(&#39;x&#39;) &amp; &quot;y&quot;&lt;/script&gt;");
  EXPECT_EQ(html_escape("unit 99 is not a servo unit"), "unit 99 is not a servo unit");
}

}  // namespace
}  // namespace sms::gateway::console
