"""What every pymodbus end-to-end script checks first, whatever the way in (Modbus TCP or an
upstream RTU port): servo 1's feedback block, then a goal written and read back."""


def feedback_and_goal(client, goal: int) -> bool:
    feedback = client.read_input_registers(56, 15, slave=1)
    if feedback.isError() or len(feedback.registers) != 15:
        print("FC04 56+15 failed:", feedback)
        return False
    print("feedback", feedback.registers)

    written = client.write_register(42, goal, slave=1)
    if written.isError():
        print("FC06 42 failed:", written)
        return False
    read_back = client.read_holding_registers(42, 1, slave=1)
    if read_back.isError() or read_back.registers != [goal]:
        print("FC03 42 gave", read_back)
        return False
    print("goal", read_back.registers[0])
    return True
