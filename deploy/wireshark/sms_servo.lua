-- sms_servo.lua: a Wireshark dissector for the servo bus frames in sms-gateway's bus monitor
-- captures (docs/MONITOR.md): Feetech `FF FF` (SCS/STS/SMS) and `D5 5D` packets on link type
-- LINKTYPE_USER0 (147). It also hands link type LINKTYPE_USER1 (148), the gateway's Modbus-RTU
-- buses, to Wireshark's own Modbus RTU dissector (mbrtu).
--
--   wireshark -X lua_script:/usr/share/sms-gateway/wireshark/sms_servo.lua capture.pcapng
--   tshark -X lua_script:/usr/share/sms-gateway/wireshark/sms_servo.lua -r capture.pcapng -V
--
-- Or copy it to ~/.local/lib/wireshark/plugins/ to have it loaded every time.
--
-- Frame: HEADER(2) ID LEN CODE PARAMS... CHK, LEN = number of params + 2. CODE is the
-- instruction in a request (to the servos) and the status byte in an answer. Checksum: the
-- inverted sum of ID..last param (FF FF), the plain sum (D5 5D). The direction comes from the
-- capture (epb_flags: outbound = to the servos).

local sms = Proto("sms_servo", "SMS servo bus")

local instructions = {
  [0x01] = "PING", [0x02] = "READ", [0x03] = "WRITE", [0x04] = "REG WRITE", [0x05] = "ACTION",
  [0x83] = "SYNC WRITE",
}
local feetech_instructions = {
  [0x06] = "RECOVERY", [0x08] = "REBOOT", [0x09] = "BACKUP", [0x0A] = "RESET STATUS", [0x0B] = "CALIBRATE",
  [0x82] = "SYNC READ",
}
local d55d_instructions = {
  [0x06] = "RESET", [0x07] = "START END", [0x0A] = "TRAJECTORY WRITE", [0x0B] = "TRAJECTORY ACTION",
  [0xFF] = "CUSTOM",
}
local feetech_status_bits = {
  {0x01, "voltage"}, {0x02, "angle_sensor"}, {0x04, "temperature"}, {0x08, "current"}, {0x10, "angle"},
  {0x20, "overload"},
}
local d55d_status_bits = {
  {0x01, "over_temperature"}, {0x02, "over_current"}, {0x04, "over_voltage"}, {0x08, "under_voltage"},
  {0x10, "checksum"}, {0x20, "instruction"}, {0x40, "stall"},
}

local f = sms.fields
f.protocol = ProtoField.string("sms_servo.protocol", "Protocol")
f.header = ProtoField.uint16("sms_servo.header", "Header", base.HEX)
f.direction = ProtoField.string("sms_servo.direction", "Direction")
f.id = ProtoField.uint8("sms_servo.id", "ID", base.DEC)
f.length = ProtoField.uint8("sms_servo.length", "Length", base.DEC)
f.instruction = ProtoField.uint8("sms_servo.instruction", "Instruction code", base.HEX)
f.instruction_name = ProtoField.string("sms_servo.instruction_name", "Instruction")
f.status = ProtoField.uint8("sms_servo.status", "Status", base.HEX)
f.status_bits = ProtoField.string("sms_servo.status_bits", "Status bits")
f.answer_to = ProtoField.string("sms_servo.answer_to", "Answer to")
f.address = ProtoField.uint8("sms_servo.address", "Start address", base.DEC)
f.count = ProtoField.uint8("sms_servo.count", "Length of data", base.DEC)
f.data = ProtoField.bytes("sms_servo.data", "Data")
f.member = ProtoField.uint8("sms_servo.member", "Servo", base.DEC)
f.params = ProtoField.bytes("sms_servo.params", "Parameters")
f.checksum = ProtoField.uint8("sms_servo.checksum", "Checksum", base.HEX)
f.checksum_ok = ProtoField.bool("sms_servo.checksum_ok", "Checksum valid")

local bad_checksum = ProtoExpert.new("sms_servo.bad_checksum", "Wrong checksum", expert.group.CHECKSUM,
                                     expert.severity.ERROR)
local bad_length = ProtoExpert.new("sms_servo.bad_length", "LEN does not match the frame", expert.group.MALFORMED,
                                   expert.severity.ERROR)
sms.experts = {bad_checksum, bad_length}

-- The instruction of the last request seen for each ID (and for the broadcast), by frame number,
-- so an answer can say what it answers (the first pass fills it; later passes read it).
local last_request = {}
local answer_names = {}

sms.init = function()
  last_request = {}
  answer_names = {}
end

local function instruction_name(d55d, code)
  local name = instructions[code] or (d55d and d55d_instructions[code]) or (not d55d and feetech_instructions[code])
  return name or string.format("instruction 0x%02X", code)
end

local function status_text(d55d, status)
  local names = {}
  for _, bit in ipairs(d55d and d55d_status_bits or feetech_status_bits) do
    if bit32.band(status, bit[1]) ~= 0 then names[#names + 1] = bit[2] end
  end
  if #names == 0 then return "none" end
  return table.concat(names, ", ")
end

function sms.dissector(buffer, pinfo, tree)
  local size = buffer:len()
  if size < 6 then return 0 end
  local first, second = buffer(0, 1):uint(), buffer(1, 1):uint()
  local d55d
  if first == 0xFF and second == 0xFF then
    d55d = false
  elseif first == 0xD5 and second == 0x5D then
    d55d = true
  else
    return 0
  end
  pinfo.cols.protocol = d55d and "D55D" or "FF FF"
  local to_servos = pinfo.p2p_dir ~= P2P_DIR_RECV
  local subtree = tree:add(sms, buffer(), "SMS servo bus, " .. (d55d and "D5 5D" or "FF FF") .. ", " ..
                           (to_servos and "request" or "answer"))
  subtree:add(f.protocol, d55d and "d55d" or "feetech")
  subtree:add(f.header, buffer(0, 2))
  subtree:add(f.direction, to_servos and "to servos" or "from servos")
  local id = buffer(2, 1):uint()
  local len = buffer(3, 1):uint()
  local code = buffer(4, 1):uint()
  subtree:add(f.id, buffer(2, 1))
  local len_item = subtree:add(f.length, buffer(3, 1))
  if len + 4 ~= size then len_item:add_proto_expert_info(bad_length) end
  local params_size = math.max(0, math.min(len, size - 4) - 2)

  local sum = 0
  for i = 2, size - 2 do sum = sum + buffer(i, 1):uint() end
  local expected = d55d and bit32.band(sum, 0xFF) or bit32.band(bit32.bnot(sum), 0xFF)

  local summary
  if to_servos then
    local name = instruction_name(d55d, code)
    subtree:add(f.instruction, buffer(4, 1))
    subtree:add(f.instruction_name, buffer(4, 1), name)
    if (code == 0x02) and params_size >= 2 then
      subtree:add(f.address, buffer(5, 1))
      subtree:add(f.count, buffer(6, 1))
      summary = string.format("%s %d+%d", name, buffer(5, 1):uint(), buffer(6, 1):uint())
    elseif (code == 0x03 or code == 0x04) and params_size >= 1 then
      subtree:add(f.address, buffer(5, 1))
      if params_size > 1 then subtree:add(f.data, buffer(6, params_size - 1)) end
      summary = string.format("%s %d (%d bytes)", name, buffer(5, 1):uint(), params_size - 1)
    elseif (code == 0x83 or (code == 0x82 and not d55d)) and params_size >= 2 then
      local address, count = buffer(5, 1):uint(), buffer(6, 1):uint()
      subtree:add(f.address, buffer(5, 1))
      subtree:add(f.count, buffer(6, 1))
      local at = 7
      local members = {}
      local step = code == 0x83 and count + 1 or 1
      while at + step <= 5 + params_size do
        local member = subtree:add(f.member, buffer(at, 1))
        if code == 0x83 and count > 0 then member:add(f.data, buffer(at + 1, count)) end
        members[#members + 1] = tostring(buffer(at, 1):uint())
        at = at + step
      end
      summary = string.format("%s %d+%d to %s", name, address, count, table.concat(members, ","))
    else
      if params_size > 0 then subtree:add(f.params, buffer(5, params_size)) end
      summary = name
    end
    if not pinfo.visited then last_request[id] = name end
    pinfo.cols.info = string.format("ID %d %s", id, summary)
  else
    subtree:add(f.status, buffer(4, 1))
    subtree:add(f.status_bits, buffer(4, 1), status_text(d55d, code))
    if not pinfo.visited then
      answer_names[pinfo.number] = last_request[id] or last_request[0xFE]
    end
    local answers = answer_names[pinfo.number]
    if answers then
      subtree:add(f.answer_to, answers)
      subtree:add(f.instruction_name, answers):set_generated()
    end
    if params_size > 0 then subtree:add(f.data, buffer(5, params_size)) end
    pinfo.cols.info = string.format("ID %d answer%s, status 0x%02X (%s)%s", id,
                                    answers and (" to " .. answers) or "", code, status_text(d55d, code),
                                    params_size > 0 and string.format(", %d data bytes", params_size) or "")
  end

  local checksum = buffer(size - 1, 1):uint()
  local checksum_item = subtree:add(f.checksum, buffer(size - 1, 1))
  subtree:add(f.checksum_ok, buffer(size - 1, 1), checksum == expected):set_generated()
  if checksum ~= expected then
    checksum_item:add_proto_expert_info(bad_checksum,
                                        string.format("Wrong checksum 0x%02X, expected 0x%02X", checksum, expected))
    pinfo.cols.info:append(" [bad checksum]")
  end
  return size
end

local encapsulations = DissectorTable.get("wtap_encap")
encapsulations:add(wtap_encaps.USER0, sms)
-- Modbus-RTU buses: Wireshark's own dissector.
local mbrtu = Dissector.get("mbrtu")
if mbrtu then encapsulations:add(wtap_encaps.USER1, mbrtu) end
