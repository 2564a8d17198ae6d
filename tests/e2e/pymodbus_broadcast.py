#!/usr/bin/python3
"""A client configured for broadcasts, as mbusd users have them: Debian's python3-pymodbus with
broadcast_enable=True sends writes to unit 0 without waiting for an answer.

Usage: pymodbus_broadcast.py PORT
Against `sms-gateway forward` in front of SMSMB servos 1 and 2: broadcasts torque_limit (0x84)
values and reads each servo back right after, three rounds. An answer to a broadcast would be
taken as the next read's answer; every read must instead give the value just broadcast.
Prints one line per step; exits 0 only when every step gave what it should.
"""
import sys

from pymodbus.client import ModbusTcpClient


def main() -> int:
    port = int(sys.argv[1])
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3, broadcast_enable=True)
    if not client.connect():
        print("cannot connect")
        return 1
    try:
        for value in (610, 620, 630):
            # pymodbus does not wait: it returns a note (bytes), not a response.
            sent = client.write_register(0x84, value, slave=0)
            if hasattr(sent, "isError") and sent.isError():
                print("broadcast FC06 failed:", sent)
                return 1
            for unit in (1, 2):
                # The line needs the broadcast's frame time first: the read queues behind it.
                read = client.read_holding_registers(0x84, 1, slave=unit)
                if read.isError() or read.registers != [value]:
                    print("unit", unit, "read after broadcast", value, "gave", read)
                    return 1
            print("broadcast", value, "read back from units 1 and 2")
    finally:
        client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
