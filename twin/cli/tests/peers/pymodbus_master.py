"""A Modbus master built on pymodbus (PyPI), driving `twin serve` the way a
SCADA would: read the input registers, write the speed set point (VEL) and the
enable coils, then watch the wheel speed (RPM_M) follow two set points.

    python3 pymodbus_master.py tcp HOST PORT
    python3 pymodbus_master.py rtu DEVICE

Prints one JSON object with what it saw; exits 1 with a message on any Modbus
error. Addresses are docs/protocols/modbus-map.md's.
"""
import json
import sys
import time

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus import FramerType

RPM_M = 3
VEL_LOW, VEL_HIGH = 1638, 3276  # 40 % and 80 % of the 12-bit DAC


def fail(msg):
    print(msg, file=sys.stderr)
    sys.exit(1)


def ok(rr, what):
    if rr.isError():
        fail(f"{what}: {rr}")
    return rr


def main():
    if sys.argv[1] == "tcp":
        client = ModbusTcpClient(sys.argv[2], port=int(sys.argv[3]), timeout=3, retries=1)
    else:
        client = ModbusSerialClient(port=sys.argv[2], framer=FramerType.RTU,
                                    baudrate=115200, timeout=3, retries=1)
    if not client.connect():
        fail("cannot connect")
    dev = 1
    seen = {}
    seen["inputs"] = ok(client.read_input_registers(0, count=10, device_id=dev), "FC04").registers
    seen["coils_before"] = ok(client.read_coils(0, count=6, device_id=dev), "FC01").bits[:6]
    ok(client.write_register(0, VEL_LOW, device_id=dev), "FC06 VEL")
    seen["vel_readback"] = ok(client.read_holding_registers(0, count=1, device_id=dev), "FC03").registers[0]
    # Coil = pin level, 0 = active: EN 0 enables, BRK 1 releases the brake.
    ok(client.write_coils(0, [False, True], device_id=dev), "FC15 EN/BRK")
    seen["coils_after"] = ok(client.read_coils(0, count=2, device_id=dev), "FC01").bits[:2]

    def rpm():
        return ok(client.read_input_registers(RPM_M, count=1, device_id=dev), "FC04 RPM_M").registers[0]

    def settle(deadline_s):
        # Settled: two readings a second apart within 2 % of each other.
        end = time.monotonic() + deadline_s
        last = rpm()
        while time.monotonic() < end:
            time.sleep(1.0)
            now = rpm()
            if now > 200 and abs(now - last) <= 0.02 * now:
                return now
            last = now
        return last

    def rise_past(target, deadline_s):
        # Following: the first reading past `target`.
        end = time.monotonic() + deadline_s
        now = rpm()
        while now <= target and time.monotonic() < end:
            time.sleep(0.2)
            now = rpm()
        return now

    seen["rpm_low"] = settle(20)
    ok(client.write_register(0, VEL_HIGH, device_id=dev), "FC06 VEL")
    seen["rpm_high"] = rise_past(1.4 * seen["rpm_low"], 20)
    client.close()
    print(json.dumps(seen))


main()
