"""A Modbus RTU slave from pymodbus on a serial port (a pseudo-terminal in the
test): unit 1, coils, holding and input registers all zero. `twin replay
--frames-to` sends it a recording's requests."""
import logging
import sys
from pymodbus import FramerType
from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext
from pymodbus.server import StartSerialServer

logging.disable(logging.WARNING)
device = ModbusDeviceContext(
    co=ModbusSequentialDataBlock(1, [False] * 64),
    di=ModbusSequentialDataBlock(1, [False] * 64),
    hr=ModbusSequentialDataBlock(1, [0] * 64),
    ir=ModbusSequentialDataBlock(1, [0] * 64),
)
context = ModbusServerContext(devices={1: device}, single=False)
print("serving", flush=True)
StartSerialServer(context, port=sys.argv[1], framer=FramerType.RTU, baudrate=115200)
