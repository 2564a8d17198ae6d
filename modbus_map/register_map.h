#pragma once
// What a Modbus client sees of one servo unit (docs/PLC_GUIDE.md), as pure functions: no I/O, no
// clock. The gateway asks for a plan, runs the plan's bus frames (or copies poll-cache bytes),
// and hands the answers back to be turned into register values. Every exception the contract
// names for addresses and values (0x02, 0x03) is decided here, with a message saying why.
//
//   FC03 / FC23 read  plan_holding_read  -> ReadPlan (bus READs)  -> registers_from(plan, replies)
//   FC04              plan_input_read    -> ReadPlan (poll cache)  -> registers_from(plan, bytes)
//   FC01              plan_coil_read     -> ReadPlan (bus READs)  -> bits_from(plan, replies)
//   FC02              plan_discrete_read -> ReadPlan (cache/bus)   -> bits_from(plan, replies)
//   FC06 / FC16 / FC23 write  plan_register_write -> WritePlan (WRITE or REG WRITE frames)
//   FC05 / FC15       plan_coil_write    -> WritePlan
//
// Addresses 1000+ (gateway facts) and unit 255 are the gateway's own; they never reach here.
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "modbus_map/control_table.h"
#include "protocol/expected.h"
#include "protocol/modbus_pdu.h"
#include "protocol/packet.h"

namespace sms::modbus_map {

// Standard Modbus exception codes (application protocol v1.1b3 §7).
enum class ModbusException : std::uint8_t {
  IllegalFunction = 0x01,
  IllegalDataAddress = 0x02,
  IllegalDataValue = 0x03,
  ServerDeviceFailure = 0x04,
  ServerDeviceBusy = 0x06,
  GatewayPathUnavailable = 0x0A,
  GatewayTargetFailedToRespond = 0x0B,
};
std::string_view to_string(ModbusException code);

// Why a request gets an exception: the code for the client, the message for the log.
struct MapError {
  ModbusException code = ModbusException::IllegalDataAddress;
  std::string message;
};
template <typename T>
using MapResult = Expected<T, MapError>;
// "exception 0x03 (illegal data value): value 5 for torque_enable (40) of table sts, ...": a
// refusal in the words a way in that checks before the router (the console, the Sparkplug node)
// answers with.
std::string to_string(const MapError& error);

// docs/PLC_GUIDE.md "Two register profiles".
enum class Profile : std::uint8_t { Native, Smsmb };
std::string_view to_string(Profile profile);  // "native", "smsmb"
std::optional<Profile> profile_from_name(std::string_view name);

// Quantity limits of the Modbus application protocol.
namespace modbus_limits = protocol::modbus_limits;

// Holding register 512 + a is the staged (REG WRITE) write of field a (packet buses only).
inline constexpr std::uint16_t kStagedWriteBase = 512;

// A run of bus addresses: bytes on packet buses, registers on modbus-rtu buses.
struct BusRange {
  std::uint16_t address = 0;
  std::uint16_t count = 0;
  std::uint32_t end() const { return std::uint32_t{address} + count; }
  bool contains(const BusRange& other) const { return other.address >= address && other.end() <= end(); }
  friend bool operator==(const BusRange&, const BusRange&) = default;
};

// The block the poll cycle reads when the configuration lists no poll fields: sts/sms1 56..70,
// d55d 36..49, smsmb registers 0x100..0x107 (the feedback block of each table).
BusRange default_poll_block(TableId table);
// The smallest block holding the named fields (configuration `poll: fields:`); the error names
// the unknown or unreadable field and the table.
Expected<BusRange> poll_block_for_fields(TableId table, std::span<const std::string> field_names);

// --- The smsmb profile's links (docs/PROTOCOL.md §2.4 right-hand column), as data ---------------------------

enum class Conversion : std::uint8_t {
  Same,        // the value as is: two's complement on Modbus <-> the field's own encoding
  Scale,       // register = field × scale_num / scale_den, rounded half away from zero
  ValueMap,    // listed value pairs (mode, lock)
  BaudRate,    // Modbus baud code <-> bit rate <-> feetech baud code
  StatusBits,  // read-only: the field's bits under status_mask
  BytePair,    // read-only: field_addr is the high byte, low_field_addr the low byte
  FaultReset,  // write-only bits: bit 2 (set centre) writes 128 to field_addr; see fault_reset_bits
};

enum class MapDirection : std::uint8_t { Both, ReadOnly, WriteOnly };
struct ValueMapping {
  std::int32_t register_value = 0;
  std::int32_t field_value = 0;
  MapDirection direction = MapDirection::Both;
};

struct CounterpartLink {
  std::uint16_t reg = 0;         // SMSMB register
  std::uint16_t field_addr = 0;  // first address of the counterpart field in the servo's table
  Conversion conversion = Conversion::Same;
  std::int32_t scale_num = 1;
  std::int32_t scale_den = 1;
  std::span<const ValueMapping> values = {};
  std::uint16_t status_mask = 0;
  std::uint16_t low_field_addr = 0;
  std::string_view notes = {};
};

// SMSMB fault-reset bits the gateway accepts: bit 2 becomes the calibration write; the others
// are accepted without a bus write (Feetech packet servos clear those faults themselves).
inline constexpr std::uint16_t kFaultResetSetCentre = 1u << 2;
inline constexpr std::uint16_t kFaultResetAcceptedBits = 0b1110'0111;
inline constexpr std::int32_t kCalibrateTorqueValue = 128;
// Shown for baud_rate (0x0B) when the servo's rate has no code in the Modbus table.
inline constexpr std::uint16_t kNoModbusBaudCode = 0xFFFF;
// The smsmb profile's input registers (FC04): the feedback block.
inline constexpr BusRange kSmsmbFeedbackRegisters{0x100, 8};

// The links of the smsmb profile for servos of `servo_table` (sts, sms1); empty for the others.
std::span<const CounterpartLink> smsmb_links(TableId servo_table);

// --- Plans ----------------------------------------------------------------------------------------

enum class RequestSpace : std::uint8_t { HoldingRegisters, InputRegisters, Coils, DiscreteInputs };
enum class ReadSource : std::uint8_t {
  Bus,        // send one READ per range (modbus-rtu: FC03), in order
  PollCache,  // copy these bus addresses out of the poll cache; no bus traffic
};

struct ReadPlan {
  RequestSpace space = RequestSpace::HoldingRegisters;
  std::uint16_t start = 0;  // the Modbus request
  std::uint16_t count = 0;
  ReadSource source = ReadSource::Bus;
  // Empty: nothing to read, every value is 0 (only gaps). Packet buses: at most one range.
  std::vector<BusRange> reads;
};

// One WRITE (or REG WRITE) frame: `data` is the bus image of [address, address + count), every
// byte belonging to a field (gap bytes are never written). modbus-rtu: registers high byte first.
struct BusWrite {
  std::uint16_t address = 0;
  protocol::Bytes data;
  friend bool operator==(const BusWrite&, const BusWrite&) = default;
};
struct WritePlan {
  bool staged = false;           // REG WRITE: runs on ACTION (gateway coil 0)
  std::vector<BusWrite> writes;  // ascending bus address; empty: nothing to send, answer OK
};

// One Modbus-visible register (or coil / discrete input) of a unit.
struct RegisterEntry {
  std::uint16_t address = 0;
  const FieldSpec* shown = nullptr;        // the field as the client sees it (name, unit, bit space)
  const FieldSpec* counterpart = nullptr;  // the servo's field; == shown on native; nullptr: none
  const CounterpartLink* link = nullptr;   // smsmb profile only
  bool readable = false;
  bool writable = false;
  std::int32_t min = 0;  // what a write accepts, as the client sees the value
  std::int32_t max = 0;
};

// A client's value for one field, as the value check took it (RegisterMap::check_write).
struct CheckedWrite {
  std::uint16_t register_value = 0;        // what a request carries for it (two's complement if signed)
  const FieldSpec* servo_field = nullptr;  // the servo's field it lands in (EEPROM or RAM: its area)
};

class RegisterMap {
 public:
  // `profile` Smsmb needs a feetech table (sts, sms1). `byte_order` overrides the table's
  // default (packet tables only: SMSMB registers are always high byte first).
  static Expected<RegisterMap> create(TableId table, Profile profile = Profile::Native,
                                      std::optional<ByteOrder> byte_order = std::nullopt);

  const TableSpec& servo_table() const { return *servo_table_; }  // spoken on the bus
  const TableSpec& shown_table() const { return *shown_table_; }  // what Modbus addresses name
  Profile profile() const { return profile_; }
  ByteOrder byte_order() const { return byte_order_; }
  std::uint8_t bytes_per_bus_address() const { return bytes_per_address(servo_table_->addressing); }
  bool supports_staged_writes() const;
  std::span<const RegisterEntry> entries() const { return entries_; }
  // The entry whose address is `address` (first address of its field), or nullptr.
  const RegisterEntry* entry_at(std::uint16_t address) const;
  // "table sts" / "smsmb profile of sts", for messages.
  const std::string& description() const { return description_; }

  // FC03 (and FC23's read): live values, one bus READ covering the range (modbus-rtu: one FC03
  // per run of readable registers).
  MapResult<ReadPlan> plan_holding_read(std::uint16_t start, std::uint16_t count) const;
  // The FC03 reads that read `entries` (readable, ascending address) live: runs the map accepts,
  // at most 125 registers each. A table whose fields leave addresses that answer 0x02 (smsmb)
  // needs several; the console's servo page and the Sparkplug node read with these.
  std::vector<BusRange> live_read_runs(std::span<const RegisterEntry* const> entries) const;
  // FC04: the same values from the poll cache; the request must lie in the unit's input window
  // (native: the poll block; smsmb profile: 0x100-0x107) and its bytes in `poll_block`.
  MapResult<ReadPlan> plan_input_read(std::uint16_t start, std::uint16_t count, BusRange poll_block) const;
  // FC01: coils (boolean RW fields), read live.
  MapResult<ReadPlan> plan_coil_read(std::uint16_t start, std::uint16_t count) const;
  // FC02: discrete inputs (boolean R fields): from the poll cache when `poll_block` holds them,
  // else live.
  MapResult<ReadPlan> plan_discrete_read(std::uint16_t start, std::uint16_t count,
                                         std::optional<BusRange> poll_block) const;

  // The request's values from the answers: one reply per plan.reads entry, in order, each
  // exactly that range's bytes (count × bytes_per_bus_address()). A short or long reply is
  // ServerDeviceFailure (0x04).
  MapResult<std::vector<std::uint16_t>> registers_from(const ReadPlan& plan,
                                                       std::span<const protocol::Bytes> replies) const;
  MapResult<std::vector<bool>> bits_from(const ReadPlan& plan, std::span<const protocol::Bytes> replies) const;

  // FC06 (one value), FC16, FC23's write. `start` >= 512: staged write of field start - 512.
  MapResult<WritePlan> plan_register_write(std::uint16_t start, std::span<const std::uint16_t> values) const;
  // FC05 (one value), FC15.
  MapResult<WritePlan> plan_coil_write(std::uint16_t start, const std::vector<bool>& values) const;

  // The one value check of a client's write (docs/PLC_GUIDE.md "Exceptions"): `value`, as the
  // client means it (signed where the field is), for the field `entry` shows — its access (0x02:
  // read-only, no counterpart), its range, its allowed values and whatever its link to the
  // servo's field accepts (0x03). plan_register_write() and plan_coil_write() run it for every
  // field they write; the console and the Sparkplug node call it before they build a request, so
  // a refusal reads the same whichever way the value came.
  MapResult<CheckedWrite> check_write(const RegisterEntry& entry, std::int64_t value) const;

  // The bus bytes of one servo field carrying `register_value` as a client wrote it, checked as
  // check_write() checks it, in this map's byte order. For sync groups (one SYNC WRITE per bus),
  // on the table's native map (a field the map does not show as itself is 0x02).
  MapResult<protocol::Bytes> field_bytes(const FieldSpec& servo_field, std::uint16_t register_value) const;

 private:
  RegisterMap() = default;

  struct FieldWrite {
    const FieldSpec* field;      // the servo's field
    std::uint32_t raw;           // its new raw value
    std::uint16_t from_address;  // the Modbus address that asked for it
  };
  MapResult<ReadPlan> plan_read(RequestSpace space, std::uint16_t start, std::uint16_t count,
                                std::optional<BusRange> poll_block) const;
  MapResult<WritePlan> plan_write(RequestSpace space, std::uint16_t start, std::span<const std::uint16_t> values) const;
  const RegisterEntry* entry_covering(std::uint16_t address) const;
  bool in_space(const RegisterEntry& entry, RequestSpace space) const;
  // 0x02 when a client may not write the field `entry` shows at all.
  std::optional<MapError> unwritable(const RegisterEntry& entry) const;
  // 0x03 when `value` (as the client means it) is outside the field's range.
  std::optional<MapError> outside_range(const RegisterEntry& entry, std::int64_t value) const;
  MapResult<std::optional<FieldWrite>> convert_write(const RegisterEntry& entry, std::uint16_t register_value) const;
  std::string field_label(const FieldSpec& field) const;
  std::string address_label(std::uint16_t address) const;

  const TableSpec* servo_table_ = nullptr;
  const TableSpec* shown_table_ = nullptr;
  Profile profile_ = Profile::Native;
  ByteOrder byte_order_ = ByteOrder::LowFirst;
  std::vector<RegisterEntry> entries_;  // one per shown field, ascending address
  std::string description_;
};

}  // namespace sms::modbus_map
