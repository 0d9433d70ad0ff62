#!/usr/bin/env python3
"""Writes the SYNTHETIC tool definition files used by the tracker tests. They are made up
(not NDI tool definitions): "NDI\\0", main type, "CF1", a 20-byte part name, marker count,
3 reserved, markers as float32 mm, zero padding, CRC-16/ARC of everything before (LE).
The simulator reads the part name to know which scene tool a handle is; it answers
ERROR40 to PINIT when the CRC does not match (a corrupt .rom)."""
import struct, os
def crc16(data):
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc
def rom(part, main_type, markers, size=176):
    b = b"NDI\0" + bytes([main_type]) + b"CF1" + part.encode().ljust(20, b" ") + bytes([len(markers), 0, 0, 0])
    for m in markers: b += struct.pack("<3f", *m)
    b = b.ljust(size - 2, b"\0")
    return b + struct.pack("<H", crc16(b))
here = os.path.dirname(os.path.abspath(__file__))
tools = {"cf_reference.rom": rom("CF-REFERENCE", 1, [(0, 0, 0), (0, 50, 0), (0, 100, 25), (0, 25, 100)]),
         "cf_pointer.rom": rom("CF-POINTER", 2, [(0, 0, 0), (-30, 0, 0), (-70, 0, 20), (-110, 0, -10)], size=200),
         "cf_camera.rom": rom("CF-CAMERA", 1, [(0, 0, 0), (40, 0, 0), (40, 40, 0), (0, 60, 10)])}
for name, data in tools.items():
    open(os.path.join(here, name), "wb").write(data)
bad = bytearray(tools["cf_pointer.rom"]); bad[40] ^= 0xFF
open(os.path.join(here, "corrupt_pointer.rom"), "wb").write(bytes(bad))
open(os.path.join(here, "not_a_rom.rom"), "wb").write(b"this is not a tool definition file\n")
