#include "gateway/tools/tool_scan.h"

#include <algorithm>
#include <array>
#include <map>
#include <optional>
#include <set>
#include <vector>

#include <fmt/format.h>

#include "gateway/bus/discovery.h"
#include "modbus_map/baud_tables.h"
#include "modbus_map/tables.h"

namespace sms::gateway {

using modbus_map::TableId;
using protocol::BusProtocol;

namespace {

// Reads of present_position per servo for the duplicate check (see the header).
constexpr int kConflictReads = 3;
// The broadcast PING that decides whether a rate is worth scanning.
constexpr unsigned kProbeAttempts = 3;
constexpr std::chrono::milliseconds kProbeExtraWait{20};
// Reads that confirm a suspected ID conflict wait this much longer.
constexpr std::chrono::milliseconds kConfirmExtraWait{20};

std::string identity_text(const ScanFinding& finding, bool model) {
  const IdentityLayout* layout = identity_layout(finding.table);
  return format_identity_value(layout, model, model ? finding.identity.model : finding.identity.firmware);
}

// What the reads that confirm a found servo heard besides its answers: other IDs' late answers,
// and bytes dropped before a request (a late answer that came between two requests).
struct HeardMeanwhile {
  std::set<std::uint8_t> ids;
  bool dropped = false;
};

LinkAnswer watched_read(ServoLink& link, HeardMeanwhile& heard, std::uint8_t id, std::uint16_t address,
                        std::uint16_t count) {
  LinkAnswer answer = link.read(id, address, count);
  heard.ids.insert(answer.other_ids.begin(), answer.other_ids.end());
  heard.dropped = heard.dropped || answer.dropped_before > 0;
  return answer;
}

// The identity, and the table the servo speaks when its byte-order flag tells (SCS or STS/SMS).
ServoIdentity read_identity(ServoLink& link, HeardMeanwhile& heard, TableId& table_id, std::uint8_t id) {
  const IdentityLayout* layout = identity_layout(table_id);
  if (layout == nullptr) return {};
  const LinkAnswer answer = watched_read(link, heard, id, layout->read.address, layout->read.count);
  if (!answer.ok()) return {};
  if (layout->read.address == 0) {
    if (const auto spoken = table_from_byte_order_flag(table_id, answer.data)) {
      table_id = *spoken;
      layout = identity_layout(table_id);
    }
  }
  return decode_identity(*layout, answer.data, modbus_map::table(table_id).default_byte_order);
}

// How many of `reads` reads of present_position come back damaged.
int damaged_position_reads(ServoLink& link, HeardMeanwhile& heard, const modbus_map::TableSpec& table,
                           const modbus_map::FieldSpec& position, std::uint8_t id, int reads) {
  const std::uint16_t span = modbus_map::address_span(table.addressing, position);
  int damaged = 0;
  for (int read = 0; read < reads; ++read) {
    if (watched_read(link, heard, id, position.addr, span).status == LinkStatus::Corrupt) ++damaged;
  }
  return damaged;
}

// True when present_position keeps coming back damaged: two servos answer on this ID. A
// damaged answer can also be a late answer overlapping the next request (a timeout shorter
// than the servo's delay on a busy machine): a suspicion is confirmed with reads that wait
// longer, and only a majority of damaged ones counts.
bool answers_collide(ServoLink& link, HeardMeanwhile& heard, TableId table_id, std::uint8_t id) {
  const auto& table = modbus_map::table(table_id);
  const modbus_map::FieldSpec* position = modbus_map::field_by_name(table, "present_position");
  if (position == nullptr) return false;
  if (damaged_position_reads(link, heard, table, *position, id, kConflictReads) == 0) return false;
  const auto latency = link.settings().latency;
  link.set_latency(latency + kConfirmExtraWait);
  const int damaged = damaged_position_reads(link, heard, table, *position, id, kConflictReads);
  link.set_latency(latency);
  return damaged * 2 > kConflictReads;
}

}  // namespace

Expected<ScanReport> scan_bus(ServoLink& link, const ScanOptions& options, const Say& say) {
  const auto started = std::chrono::steady_clock::now();
  const BusProtocol protocol = link.settings().protocol;
  const ToolProtocol& rules = tool_protocol(protocol);
  if (modbus_map::table(options.table).protocol != protocol) {
    return unexpected(fmt::format("table {} is not spoken on {} buses", modbus_map::table(options.table).name,
                                  protocol::to_string(protocol)));
  }
  ScanReport report;
  report.protocol = protocol;
  report.table = options.table;
  if (options.bauds.empty()) {
    for (const auto& entry : modbus_map::baud_table(protocol)) report.bauds.push_back(entry.bps);
  } else {
    for (const std::uint32_t baud : options.bauds) {
      if (auto code = modbus_map::baud_code(protocol, baud); !code) return unexpected(code.error());
      report.bauds.push_back(baud);
    }
  }
  std::vector<std::uint8_t> ids = options.ids;
  if (ids.empty()) {
    for (unsigned id = rules.first_id; id <= rules.last_id; ++id) ids.push_back(static_cast<std::uint8_t>(id));
  }
  for (const std::uint8_t id : ids) {
    if (id < rules.first_id || id > rules.last_id) {
      return unexpected(fmt::format("ID {} is not a servo ID on {} buses ({}-{})", id, protocol::to_string(protocol),
                                    rules.first_id, rules.last_id));
    }
  }
  report.ids_per_baud = ids.size();

  const unsigned attempts = link.settings().attempts;
  link.set_attempts(1);  // a scan asks each ID once; an answer is confirmed by the reads after it
  for (const std::uint32_t baud : report.bauds) {
    const auto baud_started = std::chrono::steady_clock::now();
    if (auto switched = link.set_baud(baud); !switched) return unexpected(switched.error());
    if (options.broadcast_probe && rules.broadcast_ping_answered) {
      // One probe decides over a whole rate: it gets three attempts and a generous wait.
      const auto latency = link.settings().latency;
      link.set_latency(latency + kProbeExtraWait);
      link.set_attempts(kProbeAttempts);
      const LinkAnswer anyone = link.ping(rules.broadcast_id);
      link.set_latency(latency);
      link.set_attempts(1);
      if (anyone.status == LinkStatus::PortError) return unexpected(anyone.detail);
      if (!anyone.heard_anything) {
        report.skipped_bauds.push_back(baud);
        say(fmt::format("{:>8} bit/s: nothing answers a broadcast PING", baud));
        continue;
      }
    }
    std::size_t at_this_baud = 0;
    const std::size_t first_at_this_baud = report.found.size();
    // IDs whose answer arrived in another ID's window: they answered late (a busy adapter or
    // host). Asked again, waiting longer, after the pass, so one slow answer does not hide a
    // servo.
    // An answer that came after its ID's wait and before the next request is dropped unread
    // when that request goes out (only the bytes are known, not the ID): the ID asked just before
    // and found silent is asked again too.
    std::set<std::uint8_t> answered_late;
    std::set<std::uint8_t> seen;
    std::optional<std::uint8_t> last_silent;
    const auto probe = [&](std::uint8_t id) -> Expected<bool> {
      LinkAnswer answer = link.ping(id);
      if (answer.status == LinkStatus::PortError) return unexpected(answer.detail);
      seen.insert(id);
      answered_late.insert(answer.other_ids.begin(), answer.other_ids.end());
      if (answer.dropped_before > 0 && last_silent) answered_late.insert(*last_silent);
      const std::optional<std::uint8_t> silent_before = answer.dropped_before > 0 ? std::nullopt : last_silent;
      last_silent = id;  // until an answer says otherwise below
      if (!answer.ok() && !answer.heard_anything) return false;
      if (!answer.ok()) {
        // Only damaged answers: several transmitters at once, or a late answer overlapping
        // ours. Ask again, waiting longer, before calling it a collision.
        const auto latency = link.settings().latency;
        link.set_latency(latency + kConfirmExtraWait);
        answer = link.ping(id);
        link.set_latency(latency);
        if (answer.status == LinkStatus::PortError) return unexpected(answer.detail);
        answered_late.insert(answer.other_ids.begin(), answer.other_ids.end());
        if (!answer.ok() && !answer.damaged) return false;  // silence, or only other IDs' late answers
      }
      ScanFinding finding;
      finding.baud = baud;
      finding.id = id;
      finding.table = options.table;
      if (answer.ok()) {
        finding.status = answer.servo_status;
        // The reads that confirm it can drop the late answer of the ID asked just before, as the
        // next ping would: that ID is asked again too.
        HeardMeanwhile heard;
        link.set_attempts(attempts);  // the identity is worth a retry; a collision check is not
        finding.identity = read_identity(link, heard, finding.table, id);
        link.set_attempts(1);
        finding.conflict = answers_collide(link, heard, options.table, id);
        answered_late.insert(heard.ids.begin(), heard.ids.end());
        if (heard.dropped && silent_before) answered_late.insert(*silent_before);
        if (finding.table != options.table) {
          finding.note = fmt::format("table {}: address 2 says {} byte first", modbus_map::table(finding.table).name,
                                     finding.table == TableId::Scs ? "high" : "low");
        }
        if (protocol == BusProtocol::ModbusRtu && answer.servo_status != 0) {
          finding.note =
              fmt::format("a Modbus slave, not an SMSMB servo (FC03 of register 0 answered exception 0x{:02X})",
                          answer.servo_status);
        }
      } else {
        finding.conflict = true;  // still only damaged answers
      }
      if (finding.conflict) {
        finding.note =
            "two or more servos answer on this ID (their replies collide): connect one at a time and "
            "give each its own ID with set-id";
      }
      report.found.push_back(std::move(finding));
      ++at_this_baud;
      last_silent.reset();
      return true;
    };
    std::set<std::uint8_t> found_here;
    for (const std::uint8_t id : ids) {
      auto probed = probe(id);
      if (!probed) return unexpected(probed.error());
      if (*probed) found_here.insert(id);
    }
    std::vector<std::uint8_t> second_look;
    for (const std::uint8_t id : answered_late) {
      if (seen.contains(id) && !found_here.contains(id)) second_look.push_back(id);
    }
    if (!second_look.empty()) {
      const auto latency = link.settings().latency;
      link.set_latency(latency + kConfirmExtraWait);
      for (const std::uint8_t id : second_look) {
        auto probed = probe(id);
        if (!probed) {
          link.set_latency(latency);
          return unexpected(probed.error());
        }
        if (*probed) say(fmt::format("{:>8} bit/s: ID {} answered late; found on a second look", baud, id));
      }
      link.set_latency(latency);
      std::sort(report.found.begin() + static_cast<std::ptrdiff_t>(first_at_this_baud), report.found.end(),
                [](const ScanFinding& a, const ScanFinding& b) { return a.id < b.id; });
    }
    const auto took =
        std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - baud_started);
    say(fmt::format("{:>8} bit/s: {} found ({} IDs in {} ms)", baud, at_this_baud, ids.size(), took.count()));
  }
  link.set_attempts(attempts);
  report.elapsed = std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - started);
  return report;
}

std::string format_scan(const ScanReport& report) {
  std::string text = fmt::format("{:>8}  {:>3}  {:<8}  {:<8}  {}\n", "baud", "id", "model", "firmware", "note");
  for (const ScanFinding& finding : report.found) {
    text += fmt::format("{:>8}  {:>3}  {:<8}  {:<8}  {}\n", finding.baud, finding.id, identity_text(finding, true),
                        identity_text(finding, false), finding.note);
  }
  const auto conflicts = std::count_if(report.found.begin(), report.found.end(),
                                       [](const ScanFinding& finding) { return finding.conflict; });
  text +=
      fmt::format("{} servo ID(s) answering on {} ({} rate(s) x {} IDs, {} rate(s) silent) in {:.1f} s",
                  report.found.size(), protocol::to_string(report.protocol), report.bauds.size(), report.ids_per_baud,
                  report.skipped_bauds.size(), static_cast<double>(report.elapsed.count()) / 1000.0);
  if (conflicts > 0) text += fmt::format("; {} ID conflict(s)", conflicts);
  return text + "\n";
}

std::string scan_config_yaml(const ScanReport& report, const LinkSettings& link) {
  // The bus runs at the rate where most servos answer cleanly (the faster one on a tie).
  std::map<std::uint32_t, std::size_t> clean_per_baud;
  for (const ScanFinding& finding : report.found) {
    if (!finding.conflict) ++clean_per_baud[finding.baud];
  }
  std::uint32_t bus_baud = link.baud;
  std::size_t best = 0;
  for (const std::uint32_t baud : report.bauds) {
    const auto found = clean_per_baud.find(baud);
    if (found != clean_per_baud.end() && found->second > best) {
      best = found->second;
      bus_baud = baud;
    }
  }
  std::string yaml = fmt::format(
      "# Written by `sms-gateway scan` on {} ({}): {} servo(s) at {} bit/s.\n"
      "# Check each servo's table (a scan tells scs from sts by address 2, not sts from sms1) and the\n"
      "# unit numbers, then:\n"
      "#   sms-gateway --check-config THIS_FILE && sms-gateway --config THIS_FILE\n"
      "# Every key and its default: config/README.md.\n\n"
      "modbus_tcp:\n  listen: 127.0.0.1:5020\n\n"
      "buses:\n  - name: bus1\n    device: \"{}\"\n    protocol: {}\n    baud: {}\n",
      link.device, protocol::to_string(report.protocol), best, bus_baud, link.device,
      protocol::to_string(report.protocol), bus_baud);
  if (report.protocol == BusProtocol::ModbusRtu) {
    yaml += fmt::format("    parity: {}\n    stop_bits: {}\n", config::to_string(link.parity), link.stop_bits);
  }
  std::string servos;
  std::set<std::uint8_t> units;
  for (const ScanFinding& finding : report.found) {
    if (finding.baud == bus_baud && !finding.conflict && finding.id >= 1 && finding.id <= 247) units.insert(finding.id);
  }
  std::string later;
  for (const ScanFinding& finding : report.found) {
    const std::string identity =
        fmt::format("model {}, firmware {}", identity_text(finding, true), identity_text(finding, false));
    if (finding.conflict) {
      later += fmt::format(
          "# ID {} at {} bit/s: two or more servos answer; give them distinct IDs (set-id) and "
          "scan again\n",
          finding.id, finding.baud);
      continue;
    }
    if (finding.baud != bus_baud) {
      later += fmt::format(
          "# ID {} answers at {} bit/s ({}): one bus runs at one rate; move it with\n"
          "#   sms-gateway set-baud --device {} --protocol {} --baud {} --id {} --new-baud {}\n",
          finding.id, finding.baud, identity, link.device, protocol::to_string(report.protocol), finding.baud,
          finding.id, bus_baud);
      continue;
    }
    std::uint8_t unit = finding.id;
    if (unit < 1 || unit > 247) {
      // IDs 0 and 248-253 cannot be units: the first free unit stands in.
      unit = 1;
      while (units.count(unit) != 0) ++unit;
      units.insert(unit);
    }
    servos += fmt::format("  - {{unit: {}, bus: bus1, id: {}, table: {}}}   # {}\n", unit, finding.id,
                          modbus_map::table(finding.table).name, identity);
  }
  yaml += servos.empty() ? "\nservos: []   # no servo answered cleanly\n" : "\nservos:\n" + servos;
  if (!later.empty()) yaml += "\n" + later;
  return yaml;
}

}  // namespace sms::gateway
