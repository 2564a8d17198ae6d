// The FUXA export of a tag list (docs/HMI.md "FUXA"): FUXA's own device model.
#include <algorithm>
#include <cctype>
#include <cmath>
#include <set>
#include <utility>

#include "gateway/tools/tag_list.h"

namespace sms::gateway {

using nlohmann::json;

// --- FUXA ----------------------------------------------------------------------------------------

namespace {

// FUXA's Modbus memory areas (server/runtime/devices/modbus: ModbusMemoryAddress).
std::string_view fuxa_memaddress(TagSpace space) {
  switch (space) {
    case TagSpace::Coil: return "000000";
    case TagSpace::Discrete: return "100000";
    case TagSpace::Input: return "300000";
    case TagSpace::Holding: return "400000";
  }
  return "";
}

// FUXA's ModbusTagType names.
std::string_view fuxa_type(const Tag& tag) {
  if (tag.space == TagSpace::Coil || tag.space == TagSpace::Discrete) return "Bool";
  if (tag.words == 2) return tag.is_signed ? "Int32" : "UInt32";
  return tag.is_signed ? "Int16" : "UInt16";
}

// FUXA shows raw / divisor and writes value × divisor.
double fuxa_divisor(double scale) {
  if (scale == 1.0) return 1.0;
  const double divisor = 1.0 / scale;
  const double magnitude = std::pow(10.0, 5 - std::floor(std::log10(divisor)));
  return std::round(divisor * magnitude) / magnitude;  // 6 significant digits
}

// FUXA's tokenized polling reads each run of adjacent tags with one request, but fills in only
// the tags of the 100-address block the run starts in (TOKEN_LIMIT in its modbus driver): a tag
// at a multiple of 100 that continues a run goes to another device of the same unit, where it
// starts a run of its own. Returns each tag's part (0: the unit's first device).
std::vector<std::size_t> fuxa_parts(const std::vector<const Tag*>& unit_tags) {
  std::vector<std::size_t> order(unit_tags.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  const auto key = [&](std::size_t i) { return std::pair{unit_tags[i]->space, unit_tags[i]->address}; };
  std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return key(a) < key(b); });
  struct Run {
    TagSpace space = TagSpace::Holding;
    std::uint32_t block = 0;  // the 100-address block it started in
    std::uint32_t end = 0;
    bool open = false;
  };
  std::vector<Run> runs;  // the current run of each part
  std::vector<std::size_t> parts(unit_tags.size(), 0);
  for (const std::size_t i : order) {
    const Tag& tag = *unit_tags[i];
    std::size_t part = 0;
    for (;; ++part) {
      if (part == runs.size()) runs.emplace_back();
      const Run& run = runs[part];
      const bool continues = run.open && run.space == tag.space && tag.address <= run.end;
      if (!continues || tag.address / 100U == run.block) break;
    }
    Run& run = runs[part];
    if (run.open && run.space == tag.space && tag.address <= run.end) {
      run.end = std::max(run.end, std::uint32_t{tag.address} + tag.words);
    } else {
      run = Run{tag.space, tag.address / 100U, std::uint32_t{tag.address} + tag.words, true};
    }
    parts[i] = part;
  }
  return parts;
}

// The gateway a device belongs to, as FUXA ids may spell it: "192_168_1_20_502". Two gateways in
// one FUXA project then keep devices of their own.
std::string fuxa_gateway_key(const FlowTarget& target) {
  std::string key = target.host + "_" + std::to_string(target.port);
  for (char& c : key) {
    if (std::isalnum(static_cast<unsigned char>(c)) == 0) c = '_';
  }
  return key;
}

json fuxa_device(const Tag& first, std::size_t part, const FlowTarget& target) {
  const std::string unit = std::to_string(first.unit);
  const std::string suffix = part == 0 ? std::string() : "_p" + std::to_string(part + 1);
  return {{"id", "d_sms_" + fuxa_gateway_key(target) + "_unit" + unit + suffix},
          {"name", "unit " + unit + " " + first.servo + (part == 0 ? "" : " (" + std::to_string(part + 1) + ")")},
          {"enabled", true},
          {"type", "ModbusTCP"},
          {"polling", 1000},
          {"property",
           // FUXA's Modbus driver takes the port from the address ("host:port"; 502 without one)
           // and shares one connection among the devices of the same address.
           {{"address", target.host + ":" + std::to_string(target.port)},
            {"port", std::to_string(target.port)},
            {"slaveid", unit},
            {"connectionOption", "TcpPort"},
            {"delay", 10},
            // FUXA's "Tokenized" switch: one read per run of adjacent tags. Without it FUXA reads
            // from the lowest to the highest tag of every 100 addresses, across addresses the
            // unit answers 0x02 for (an smsmb register the servo lacks, the gaps between sync
            // groups).
            {"options", true}}},
          {"tags", json::object()}};
}

json fuxa_tag(const Tag& tag) {
  const std::string id =
      "t_u" + std::to_string(tag.unit) + "_" + std::string(to_string(tag.space)) + "_" + std::to_string(tag.address);
  const std::string name =
      tag.space == TagSpace::Holding ? tag.name : tag.name + " (" + std::string(to_string(tag.space)) + ")";
  std::string description = tag.symbol.empty() ? std::string() : "in " + tag.symbol;
  if (!tag.notes.empty()) description += (description.empty() ? "" : "; ") + tag.notes;
  return {{"id", id},
          {"name", name},
          {"label", name},
          {"type", fuxa_type(tag)},
          {"memaddress", fuxa_memaddress(tag.space)},
          {"address", std::to_string(address_1based(tag))},
          {"divisor", fuxa_divisor(tag.scale)},
          {"access", access_text(tag)},
          {"description", description},
          {"daq", {{"enabled", false}, {"changed", false}, {"interval", 60}, {"restored", false}}}};
}

}  // namespace

json fuxa_devices(const std::vector<Tag>& tags, const FlowTarget& target) {
  // FUXA polls every tag it has, each second: a field the poll cache serves (an input register
  // tag) is read from there, not live over the bus as well (its read-only holding tag is left out).
  std::set<std::pair<std::uint8_t, std::uint16_t>> cached;
  for (const Tag& tag : tags) {
    if (tag.space == TagSpace::Input) cached.emplace(tag.unit, tag.address);
  }
  const auto polled_twice = [&](const Tag& tag) {
    return tag.space == TagSpace::Holding && !tag.writable && cached.contains({tag.unit, tag.address});
  };
  json devices = json::array();
  for (std::size_t begin = 0; begin < tags.size();) {
    std::size_t end = begin;
    std::vector<const Tag*> unit_tags;
    for (; end < tags.size() && tags[end].unit == tags[begin].unit; ++end) {
      if (!polled_twice(tags[end])) unit_tags.push_back(&tags[end]);
    }
    const std::vector<std::size_t> parts = fuxa_parts(unit_tags);
    const std::size_t count = *std::max_element(parts.begin(), parts.end()) + 1;
    for (std::size_t part = 0; part < count; ++part) {
      json device = fuxa_device(tags[begin], part, target);
      for (std::size_t i = 0; i < unit_tags.size(); ++i) {
        if (parts[i] != part) continue;
        json tag = fuxa_tag(*unit_tags[i]);
        const std::string id = tag["id"];
        device["tags"][id] = std::move(tag);
      }
      devices.push_back(std::move(device));
    }
    begin = end;
  }
  return devices;
}

}  // namespace sms::gateway
