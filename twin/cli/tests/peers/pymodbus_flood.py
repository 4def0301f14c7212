"""Several pymodbus (PyPI) masters polling `twin serve` over Modbus TCP back
to back, each on its own connection and thread, for a given time: FC04 ten
input registers and FC03 three holding registers, alternating.

    python3 pymodbus_flood.py HOST PORT CLIENTS SECONDS

Prints one JSON object: requests sent, answered, and Modbus errors. A request
whose reply did not come is counted sent and not answered.
"""
import json
import sys
import threading
import time

from pymodbus.client import ModbusTcpClient


def main():
    host, port, clients, seconds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
    totals = {"sent": 0, "answered": 0, "errors": 0}
    lock = threading.Lock()
    start = threading.Barrier(clients)

    def poll():
        client = ModbusTcpClient(host, port=port, timeout=5, retries=0)
        if not client.connect():
            print("cannot connect", file=sys.stderr)
            sys.exit(1)
        sent = answered = errors = 0
        start.wait()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            sent += 1
            try:
                if sent % 2:
                    rr = client.read_input_registers(0, count=10, device_id=1)
                else:
                    rr = client.read_holding_registers(0, count=3, device_id=1)
            except Exception as e:  # noqa: BLE001 - counted, and the run goes on
                print(f"request failed: {e}", file=sys.stderr)
                continue
            answered += 1
            if rr.isError():
                errors += 1
        client.close()
        with lock:
            totals["sent"] += sent
            totals["answered"] += answered
            totals["errors"] += errors

    threads = [threading.Thread(target=poll) for _ in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print(json.dumps(totals))


main()
