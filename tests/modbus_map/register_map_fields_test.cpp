// Every field of every table through the native register map: a read of its address gives its
// value from hand-built bus bytes, a write of that value produces exactly those bytes.
#include <gtest/gtest.h>

#include <algorithm>
#include <string>
#include <vector>

#include "modbus_map/register_map.h"
#include "modbus_map/tables.h"

namespace sms::modbus_map {
namespace {

using protocol::Bytes;

struct FieldCase {
  std::uint16_t addr;
  Bytes bus;          // the field's bytes on the bus, in the table's byte order
  std::uint16_t reg;  // the Modbus register value
};

void expect_every_field_maps(TableId id, const std::vector<FieldCase>& cases) {
  const TableSpec& spec = table(id);
  const auto map = RegisterMap::create(id);
  ASSERT_TRUE(map) << map.error();
  for (const FieldSpec& field : spec.fields) {
    const bool covered =
        std::any_of(cases.begin(), cases.end(), [&](const FieldCase& c) { return c.addr == field.addr; });
    EXPECT_TRUE(covered) << spec.name << ": no case for field " << field.name << " (" << field.addr << ")";
  }
  const std::uint16_t span = spec.addressing == Addressing::Register ? 1 : 0;
  for (const FieldCase& c : cases) {
    SCOPED_TRACE(std::string(spec.name) + " address " + std::to_string(c.addr));
    const FieldSpec* field = field_at(spec, c.addr);
    ASSERT_NE(field, nullptr);
    const auto plan = map->plan_holding_read(c.addr, 1);
    ASSERT_TRUE(plan) << plan.error().message;
    if (field->access == Access::WriteOnly) {
      EXPECT_TRUE(plan->reads.empty());
    } else {
      ASSERT_EQ(plan->reads.size(), 1u);
      EXPECT_EQ(plan->reads[0], (BusRange{c.addr, static_cast<std::uint16_t>(span != 0 ? span : c.bus.size())}));
      EXPECT_EQ(plan->source, ReadSource::Bus);
      const std::vector<Bytes> replies{c.bus};
      const auto values = map->registers_from(*plan, replies);
      ASSERT_TRUE(values) << values.error().message;
      EXPECT_EQ(*values, std::vector<std::uint16_t>{c.reg});
    }
    const std::vector<std::uint16_t> written{c.reg};
    const auto write = map->plan_register_write(c.addr, written);
    if (field->access == Access::ReadOnly) {
      ASSERT_FALSE(write);
      EXPECT_EQ(write.error().code, ModbusException::IllegalDataAddress);
    } else {
      ASSERT_TRUE(write) << write.error().message;
      EXPECT_FALSE(write->staged);
      EXPECT_EQ(write->writes, (std::vector<BusWrite>{BusWrite{c.addr, c.bus}}));
    }
  }
}

TEST(NativeMapEveryField, Sts) {
  expect_every_field_maps(TableId::Sts, {
                                            {0, {0x02}, 2},
                                            {1, {0x30}, 48},
                                            {2, {0x00}, 0},
                                            {3, {0x08}, 8},
                                            {4, {0x2A}, 42},
                                            {5, {0x07}, 7},
                                            {6, {0x04}, 4},
                                            {7, {0xFA}, 250},
                                            {8, {0x01}, 1},
                                            {9, {0x00, 0x01}, 256},
                                            {11, {0xFF, 0x0F}, 4095},
                                            {13, {0x46}, 70},
                                            {14, {0xFE}, 254},
                                            {15, {0x46}, 70},
                                            {16, {0xE8, 0x03}, 1000},
                                            {18, {0x0C}, 12},
                                            {19, {0x2C}, 44},
                                            {20, {0x2D}, 45},
                                            {21, {0x20}, 32},
                                            {22, {0x1F}, 31},
                                            {23, {0x00}, 0},
                                            {24, {0x0A}, 10},
                                            {25, {0x03}, 3},
                                            {26, {0x01}, 1},
                                            {27, {0x02}, 2},
                                            {28, {0xF4, 0x01}, 500},
                                            {30, {0x01}, 1},
                                            {31, {0x64, 0x08}, 0xFF9C},  // -100, sign bit 11
                                            {33, {0x03}, 3},
                                            {34, {0x14}, 20},
                                            {35, {0xC8}, 200},
                                            {36, {0x50}, 80},
                                            {37, {0x10}, 16},
                                            {38, {0xC8}, 200},
                                            {39, {0x05}, 5},
                                            {40, {0x80}, 128},
                                            {41, {0x0A}, 10},
                                            {42, {0xE8, 0x83}, 0xFC18},  // -1000, sign bit 15
                                            {44, {0xF4, 0x05}, 0xFE0C},  // -500, sign bit 10
                                            {46, {0xC4, 0x09}, 2500},
                                            {48, {0xE8, 0x03}, 1000},
                                            {55, {0x00}, 0},
                                            {56, {0x18, 0x05}, 1304},    // docs/PROTOCOL.md §1.1 worked READ
                                            {58, {0xC8, 0x80}, 0xFF38},  // -200
                                            {60, {0x2C, 0x05}, 0xFED4},  // -300, sign bit 10
                                            {62, {0x79}, 121},
                                            {63, {0x1E}, 30},
                                            {64, {0x01}, 1},
                                            {65, {0x24}, 0x24},
                                            {66, {0x01}, 1},
                                            {67, {0xD0, 0x87}, 0xF830},  // -2000, sign bit 15
                                            {69, {0x64, 0x00}, 100},
                                        });
}

TEST(NativeMapEveryField, Sms1) {
  expect_every_field_maps(TableId::Sms1, {
                                             {3, {0x01, 0x01}, 0x0101},
                                             {5, {0x03}, 3},
                                             {6, {0x07}, 7},
                                             {7, {0x00}, 0},
                                             {8, {0x00}, 0},
                                             {9, {0x00, 0x00}, 0},
                                             {11, {0xFF, 0x0F}, 4095},
                                             {13, {0x50}, 80},
                                             {14, {0x8C}, 140},
                                             {15, {0x3C}, 60},
                                             {16, {0xE8, 0x03}, 1000},
                                             {18, {0x01}, 1},
                                             {19, {0x2F}, 47},
                                             {20, {0x2F}, 47},
                                             {21, {0x0F}, 15},
                                             {22, {0x02}, 2},
                                             {23, {0x03}, 3},
                                             {24, {0x32, 0x00}, 50},
                                             {26, {0x01}, 1},
                                             {27, {0x01}, 1},
                                             {28, {0x00, 0x02}, 512},
                                             {30, {0x04}, 4},
                                             {31, {0x05}, 5},
                                             {32, {0x06}, 6},
                                             {33, {0x00, 0x0C}, 0xFC00},  // -1024, sign bit 11
                                             {35, {0x02}, 2},
                                             {36, {0x07, 0x00}, 7},
                                             {40, {0x01}, 1},
                                             {41, {0x0A}, 10},
                                             {42, {0x00, 0x08}, 2048},
                                             {44, {0xE8, 0x07}, 0xFC18},  // -1000, sign bit 10
                                             {46, {0xF4, 0x81}, 0xFE0C},  // -500, sign bit 15
                                             {48, {0x01}, 1},
                                             {56, {0x0A, 0x80}, 0xFFF6},  // -10, sign bit 15 (SMSCL SDK)
                                             {58, {0x0A, 0x80}, 0xFFF6},  // -10
                                             {60, {0xF4, 0x05}, 0xFE0C},  // -500, sign bit 10 (SMSCL SDK)
                                             {62, {0x78}, 120},
                                             {63, {0x20}, 32},
                                             {64, {0x01}, 1},
                                             {65, {0x04}, 4},
                                             {66, {0x00}, 0},
                                             {67, {0x00, 0x04}, 1024},
                                             {69, {0x0A, 0x80}, 0xFFF6},
                                         });
}

TEST(NativeMapEveryField, ScsHighByteFirst) {
  expect_every_field_maps(
      TableId::Scs, {
                        {0, {0x01}, 1},           {1, {0x00}, 0},
                        {2, {0x01}, 1},           {3, {0x05}, 5},
                        {4, {0x04}, 4},           {5, {0x03}, 3},
                        {6, {0x07}, 7},           {7, {0x00}, 0},
                        {8, {0x01}, 1},           {9, {0x00, 0x00}, 0},
                        {11, {0x03, 0xFF}, 1023}, {13, {0x46}, 70},
                        {14, {0x5A}, 90},         {15, {0x28}, 40},
                        {16, {0x03, 0xE8}, 1000}, {19, {0x25}, 37},
                        {20, {0x25}, 37},         {21, {0x0F}, 15},
                        {22, {0x00}, 0},          {23, {0x00}, 0},
                        {24, {0x00, 0x32}, 50},   {26, {0x01}, 1},
                        {27, {0x02}, 2},          {40, {0x02}, 2},
                        {42, {0x02, 0x00}, 512},  {44, {0x05, 0xF4}, 0xFE0C},  // -500, sign bit 10, high byte first
                        {46, {0x05, 0xDC}, 1500}, {48, {0x00}, 0},
                        {56, {0x03, 0xE8}, 1000}, {58, {0x80, 0x0A}, 0xFFF6},  // -10, sign bit 15
                        {60, {0x01, 0xF4}, 500},  {62, {0x4A}, 74},
                        {63, {0x20}, 32},         {64, {0x01}, 1},
                        {65, {0x01}, 1},          {66, {0x00}, 0},
                        {69, {0x00, 0x0A}, 10},
                    });
}

TEST(NativeMapEveryField, D55d) {
  expect_every_field_maps(TableId::D55d, {
                                             {0, {0x5D}, 0x5D},
                                             {2, {0x01}, 1},
                                             {3, {0x01}, 1},
                                             {4, {0x04}, 4},
                                             {5, {0x10}, 16},
                                             {6, {0x00, 0x00}, 0},
                                             {8, {0x10, 0x0E}, 3600},
                                             {11, {0x85}, 0xFFFB},  // -5 °C, sign bit 7
                                             {12, {0x1E}, 30},
                                             {13, {0x0A}, 10},
                                             {16, {0x02}, 2},
                                             {17, {0x01}, 1},
                                             {18, {0x7F}, 127},
                                             {19, {0x02}, 2},
                                             {20, {0x01}, 1},
                                             {21, {0x24}, 36},
                                             {22, {0x24}, 36},
                                             {24, {0x01}, 1},
                                             {25, {0x01}, 1},
                                             {30, {0x84, 0x03}, 900},
                                             {32, {0x2C, 0x81}, 0xFED4},  // -300, sign bit 15
                                             {34, {0x24}, 36},
                                             {35, {0x12}, 18},
                                             {36, {0x20, 0x03}, 800},
                                             {38, {0x18, 0xFC}, 0xFC18},  // -1000, two's complement
                                             {40, {0x00, 0x80}, 0x8000},  // -32768
                                             {42, {0x01}, 1},
                                             {43, {0x01}, 1},
                                             {44, {0x00}, 0},
                                             {46, {0x9E}, 0xFFE2},  // -30 °C, sign bit 7
                                             {47, {0x00}, 0},
                                             {48, {0x03}, 3},
                                             {49, {0x01}, 1},
                                         });
}

TEST(NativeMapEveryField, SmsmbRegistersHighByteFirst) {
  expect_every_field_maps(
      TableId::Smsmb, {
                          {0x00, {0x00, 0x03}, 3},      {0x01, {0x00, 0x09}, 9},       {0x02, {0x07, 0xE6}, 2022},
                          {0x03, {0x00, 0x0B}, 11},     {0x0A, {0x00, 0x01}, 1},       {0x0B, {0x00, 0x02}, 2},
                          {0x0C, {0x01, 0xF4}, 500},    {0x0D, {0x00, 0x00}, 0},       {0x0E, {0x0F, 0xFF}, 4095},
                          {0x0F, {0xFF, 0x9C}, 0xFF9C}, {0x10, {0x00, 0x04}, 4},       {0x11, {0x00, 0x20}, 32},
                          {0x12, {0x00, 0x20}, 32},     {0x13, {0x00, 0x00}, 0},       {0x14, {0x00, 0x0A}, 10},
                          {0x15, {0x00, 0x01}, 1},      {0x80, {0xFC, 0x18}, 0xFC18},  {0x81, {0x00, 0x01}, 1},
                          {0x82, {0x00, 0x0A}, 10},     {0x83, {0xFF, 0x9C}, 0xFF9C},  {0x84, {0x03, 0xE8}, 1000},
                          {0x85, {0x00, 0x80}, 128},    {0x86, {0x00, 0x04}, 4},       {0x100, {0x00, 0x10}, 0x10},
                          {0x101, {0x08, 0x00}, 2048},  {0x102, {0xFF, 0xF6}, 0xFFF6}, {0x103, {0xFE, 0x0C}, 0xFE0C},
                          {0x104, {0x00, 0x78}, 120},   {0x105, {0x00, 0x1E}, 30},     {0x106, {0x00, 0x01}, 1},
                          {0x107, {0x00, 0x64}, 100},   {0x180, {0x00, 0x05}, 5},      {0x181, {0x00, 0x06}, 6},
                          {0x182, {0x00, 0x64}, 100},   {0x183, {0x00, 0x02}, 2},      {0x184, {0x00, 0x32}, 50},
                          {0x185, {0x00, 0x0A}, 10},    {0x186, {0x00, 0x01}, 1},      {0x187, {0x00, 0x01}, 1},
                          {0x188, {0x00, 0x81}, 129},   {0x189, {0x00, 0x25}, 37},     {0x18A, {0x00, 0x25}, 37},
                          {0x18B, {0x00, 0x46}, 70},    {0x18C, {0x00, 0x8C}, 140},    {0x18D, {0x00, 0x28}, 40},
                          {0x18E, {0x01, 0xF4}, 500},   {0x18F, {0x07, 0xD0}, 2000},   {0x190, {0x00, 0xC8}, 200},
                          {0x191, {0x03, 0x20}, 800},   {0x192, {0x07, 0xD0}, 2000},   {0x193, {0x00, 0x01}, 1},
                          {0x194, {0x03, 0xE8}, 1000},  {0x195, {0x00, 0x00}, 0},      {0x196, {0x00, 0x59}, 89},
                      });
}

}  // namespace
}  // namespace sms::modbus_map
