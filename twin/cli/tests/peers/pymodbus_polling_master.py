"""A Modbus master built on pymodbus (PyPI) that polls for ever, as a SCADA
does: the ten input registers (FC04) of one slave, then a short pause;
a timeout, an exception or a bad frame is counted and the polling goes on.

    python3 pymodbus_polling_master.py rtu DEVICE [SECONDS]
    python3 pymodbus_polling_master.py tcp HOST PORT [SECONDS]

Addresses are docs/protocols/modbus-map.md's. Prints what it counted.
"""
import sys
import time

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException


def main():
    if sys.argv[1] == "tcp":
        client = ModbusTcpClient(sys.argv[2], port=int(sys.argv[3]), timeout=1, retries=0)
        rest = sys.argv[4:]
    else:
        client = ModbusSerialClient(port=sys.argv[2], framer=FramerType.RTU,
                                    baudrate=115200, timeout=1, retries=0)
        rest = sys.argv[3:]
    seconds = float(rest[0]) if rest else 120
    if not client.connect():
        print("cannot connect", file=sys.stderr)
        sys.exit(1)
    counts = {"good": 0, "exceptions": 0, "errors": 0}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            rr = client.read_input_registers(0, count=10, device_id=1)
            counts["exceptions" if rr.isError() else "good"] += 1
        except ModbusException:
            counts["errors"] += 1
        time.sleep(0.05)
    print(counts)


main()
