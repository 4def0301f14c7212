"""One student's Modbus master (pymodbus, PyPI) against their own module of a
class served by one `twin serve`: it connects from SOURCE (an address of
this machine: 127.0.0.1, 127.0.0.2, ...), reads the input registers, writes
its own speed set point VEL and reads it back, twice with a pause between,
so a module that another student's writes reached would show it.

    python3 pymodbus_class.py SOURCE HOST PORT VEL

Prints one JSON object: what it read, or the error it met (a refused
client's read fails). Addresses are docs/protocols/modbus-map.md's.
"""
import json
import sys
import time

from pymodbus.client import ModbusTcpClient


def main():
    source, host, port, vel = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    client = ModbusTcpClient(host, port=port, timeout=2, retries=0,
                             source_address=(source, 0))
    seen = {"connected": bool(client.connect())}
    try:
        rr = client.read_input_registers(0, count=6, device_id=1)
        if rr.isError():
            raise RuntimeError(str(rr))
        seen["inputs"] = rr.registers
        readback = []
        for _ in range(2):
            wr = client.write_register(0, vel, device_id=1)
            if wr.isError():
                raise RuntimeError(str(wr))
            time.sleep(0.5)
            rr = client.read_holding_registers(0, count=1, device_id=1)
            if rr.isError():
                raise RuntimeError(str(rr))
            readback.append(rr.registers[0])
        seen["vel_readback"] = readback
    except Exception as e:  # the refused client's failure is its result
        seen["error"] = f"{type(e).__name__}: {e}"
    client.close()
    print(json.dumps(seen))


main()
