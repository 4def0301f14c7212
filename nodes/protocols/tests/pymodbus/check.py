#!/usr/bin/env python3
"""Cross-check of the protocols crate's Modbus codecs against pymodbus.

Reads JSON lines from stdin, one per case:
  {"framer": "rtu"|"ascii"|"socket", "kind": "request"|"response",
   "hex": <frame emitted by the Rust codec>, "pdu": {fields}}
and writes one JSON line per case:
  {"decoded": {fields pymodbus read from "hex"} or {"error": ...},
   "built_hex": <the same PDU built and framed by pymodbus>}

Fields: fc, dev_id, tid, address, count, bits, registers, exception_code.
Only pymodbus' own framers (pymodbus.framer) and PDU classes (pymodbus.pdu)
do the work here; this script just maps fields in and out.
"""

import json
import sys

REQUIRED = "3.16.1"

try:
    import pymodbus
    from pymodbus.framer import FramerAscii, FramerRTU, FramerSocket
    from pymodbus.pdu import DecodePDU, ExceptionResponse
    from pymodbus.pdu import bit_message as bm
    from pymodbus.pdu import register_message as rm
except ImportError as err:  # pragma: no cover - the Rust test reports this
    sys.stderr.write(
        f"pymodbus is not importable ({err}): pip install pymodbus=={REQUIRED}\n"
    )
    sys.exit(2)

if not pymodbus.__version__.startswith("3."):
    sys.stderr.write(
        f"pymodbus {pymodbus.__version__} found, 3.x needed: "
        f"pip install pymodbus=={REQUIRED}\n"
    )
    sys.exit(2)

FRAMERS = {"rtu": FramerRTU, "ascii": FramerAscii, "socket": FramerSocket}

REQUESTS = {
    1: bm.ReadCoilsRequest,
    2: bm.ReadDiscreteInputsRequest,
    3: rm.ReadHoldingRegistersRequest,
    4: rm.ReadInputRegistersRequest,
    5: bm.WriteSingleCoilRequest,
    6: rm.WriteSingleRegisterRequest,
    15: bm.WriteMultipleCoilsRequest,
    16: rm.WriteMultipleRegistersRequest,
}

RESPONSES = {
    1: bm.ReadCoilsResponse,
    2: bm.ReadDiscreteInputsResponse,
    3: rm.ReadHoldingRegistersResponse,
    4: rm.ReadInputRegistersResponse,
    5: bm.WriteSingleCoilResponse,
    6: rm.WriteSingleRegisterResponse,
    15: bm.WriteMultipleCoilsResponse,
    16: rm.WriteMultipleRegistersResponse,
}


def fields(pdu):
    return {
        "fc": pdu.function_code,
        "dev_id": pdu.dev_id,
        "tid": pdu.transaction_id,
        "address": pdu.address,
        "count": pdu.count,
        "bits": [int(b) for b in pdu.bits],
        "registers": list(pdu.registers),
        "exception_code": pdu.exception_code,
    }


def build(kind, f):
    """A pymodbus PDU object from the case's fields."""
    fc, dev_id, tid = f["fc"], f["dev_id"], f["tid"]
    common = {"dev_id": dev_id, "transaction_id": tid}
    if fc & 0x80:
        return ExceptionResponse(
            fc & 0x7F, f["exception_code"], device_id=dev_id, transaction=tid
        )
    cls = (REQUESTS if kind == "request" else RESPONSES)[fc]
    bits = [bool(b) for b in f.get("bits", [])]
    registers = f.get("registers", [])
    address = f.get("address", 0)
    if kind == "request":
        if fc in (1, 2, 3, 4):
            return cls(address=address, count=f["count"], **common)
        if fc == 5:
            return cls(address=address, bits=bits, **common)
        if fc == 6:
            return cls(address=address, registers=registers, **common)
        if fc == 15:
            return cls(address=address, bits=bits, **common)
        return cls(address=address, registers=registers, **common)
    if fc in (1, 2):
        return cls(bits=bits, **common)
    if fc in (3, 4):
        return cls(registers=registers, **common)
    if fc == 5:
        return cls(address=address, bits=bits, **common)
    if fc == 6:
        return cls(address=address, registers=registers, **common)
    return cls(address=address, count=f["count"], **common)


def main():
    for line in sys.stdin:
        if not line.strip():
            continue
        case = json.loads(line)
        framer_cls = FRAMERS[case["framer"]]
        is_server = case["kind"] == "request"
        out = {}
        try:
            framer = framer_cls(DecodePDU(is_server))
            used, pdu = framer.handleFrame(bytes.fromhex(case["hex"]), 0, 0)
            if pdu is None:
                out["decoded"] = {"error": f"no frame (used {used} bytes)"}
            else:
                out["decoded"] = fields(pdu)
        except Exception as err:  # noqa: BLE001 - reported back to the test
            out["decoded"] = {"error": repr(err)}
        try:
            framer = framer_cls(DecodePDU(is_server))
            out["built_hex"] = framer.buildFrame(build(case["kind"], case["pdu"])).hex()
        except Exception as err:  # noqa: BLE001
            out["built_hex"] = None
            out["build_error"] = repr(err)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
