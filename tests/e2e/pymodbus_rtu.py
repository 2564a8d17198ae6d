#!/usr/bin/python3
"""An RTU master nobody here wrote: Debian's python3-pymodbus serial client on a pty.

Usage: pymodbus_rtu.py DEVICE BAUD PARITY GOAL
Against sms-gateway's upstream Modbus RTU port (--rtu-slave) in front of sts servos 1-6:
reads the feedback block of unit 1 (input registers 56-70), writes GOAL to its goal position
(holding 42), reads it back live, then asks unit 99 (not served) and expects no answer (a
serial slave that is not addressed stays silent). Prints one line per step; exits 0 only when
every step gave what it should.
"""
import sys

from pymodbus.client import ModbusSerialClient

from pymodbus_checks import feedback_and_goal


def main() -> int:
    device, baud, parity, goal = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
    # strict=False: an answer is read until it is whole or the timeout passes. pymodbus's strict
    # mode (above 19200 bit/s an inter-byte timeout of 0) takes the first burst for the whole
    # answer, which a pty relay on a loaded machine may deliver in two.
    client = ModbusSerialClient(port=device, baudrate=baud, parity=parity, stopbits=1, timeout=1, retries=0,
                                strict=False)
    if not client.connect():
        print("cannot open", device)
        return 1
    try:
        if not feedback_and_goal(client, goal):
            return 1

        try:
            silent = client.read_holding_registers(42, 1, slave=99)
            answered = not silent.isError() or "No response" not in str(silent)
        except Exception as error:  # pymodbus raises on no response in some versions
            answered = "No response" not in str(error) and "no response" not in str(error).lower()
        if answered:
            print("unit 99 answered:", silent)
            return 1
        print("unit 99 silent")
        return 0
    finally:
        client.close()


if __name__ == "__main__":
    sys.exit(main())
