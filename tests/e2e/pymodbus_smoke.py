#!/usr/bin/python3
"""Smoke test with a Modbus client nobody here wrote: Debian's python3-pymodbus.

Usage: pymodbus_smoke.py PORT GOAL
Reads the feedback block of unit 1 (input registers 56-70, from the poll cache), writes GOAL
to its goal position (holding 42), reads it back live (holding 42), reads the gateway unit's
version (unit 255, input registers 0-2), and asks unit 99 (not configured) for exception 0x0A.
Prints one line per step; exits 0 only when every step gave what the contract says.
"""
import sys

from pymodbus.client import ModbusTcpClient
from pymodbus.pdu import ExceptionResponse

from pymodbus_checks import feedback_and_goal


def main() -> int:
    port, goal = int(sys.argv[1]), int(sys.argv[2])
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    if not client.connect():
        print("cannot connect")
        return 1
    try:
        if not feedback_and_goal(client, goal):
            return 1

        version = client.read_input_registers(0, 3, slave=255)
        if version.isError():
            print("gateway unit version failed:", version)
            return 1
        print("version", ".".join(str(v) for v in version.registers))

        unknown = client.read_holding_registers(0, 1, slave=99)
        if not isinstance(unknown, ExceptionResponse) or unknown.exception_code != 0x0A:
            print("unit 99 gave", unknown)
            return 1
        print("unit 99 exception", unknown.exception_code)
        return 0
    finally:
        client.close()


if __name__ == "__main__":
    sys.exit(main())
