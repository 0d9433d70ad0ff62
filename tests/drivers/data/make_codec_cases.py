#!/usr/bin/env python3
"""Writes the codec test cases (codec/*.json) from the protocol fact sheet, with its own
CRC-16/ARC and struct packing, independent of the C++ codec. Run once; the JSON is committed.
Hex examples marked 'spec' are copied from the fact sheet (ndi-combined-api.md §2.4, §6.3)."""
import json, struct, os

def crc16(data: bytes) -> int:
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc

def ascii_reply(payload: str) -> bytes:
    return payload.encode() + b"%04X" % crc16(payload.encode()) + b"\r"

def binary_reply(body: bytes) -> bytes:
    hdr = b"\xc4\xa5" + struct.pack("<H", len(body))
    return hdr + struct.pack("<H", crc16(hdr)) + body + struct.pack("<H", crc16(body))

def bx_valid(handle, q, t, err, port, frame):
    return bytes([handle, 1]) + struct.pack("<8f", *q, *t, err) + struct.pack("<II", port, frame)

def bx_missing(handle, port, frame):
    return bytes([handle, 2]) + struct.pack("<II", port, frame)

def f32(x):
    return struct.unpack("<f", struct.pack("<f", x))[0]

def tool(handle, status, q=None, t=None, err=None, port=0, frame=0, text=False):
    d = {"handle": handle, "status": status, "port_status": port, "frame": frame}
    r = (lambda v: v) if text else f32  # BX carries float32, TX decimal text
    if q is not None:
        d.update(q=[r(v) for v in q], t_mm=[r(v) for v in t], rms_mm=r(err))
    return d

cases = {}
H = lambda b: b.hex()

# 1. The fact sheet's own BX examples (§6.3), bytes verbatim.
spec_valid = "c4a52d003043010101" "8104353f000000008104353f0000000000004841000009c20080bbc424b9fc3d" "31000000eb0300000000ae39"
spec_missing = "c4a50d002983010102" "11000000f1030000" "0000f58b"
cases["bx_spec_examples"] = {
    "source": "fact sheet §6.3 (peer test), verbatim",
    "chunks": [spec_valid, spec_missing],
    "expect": [
        {"kind": "bx", "options": "0801", "system_status": 0,
         "tools": [tool(1, "ok", [0.7071, 0, 0.7071, 0], [12.5, -34.25, -1500], 0.1234, 0x31, 1003)]},
        {"kind": "bx", "options": "0801", "system_status": 0, "tools": [tool(1, "missing", port=0x11, frame=1009)]},
    ],
    "counters": {"replies": 2, "crc_errors": 0, "resyncs": 0}}

# 2. Three tools: ok, missing, disabled; out-of-volume and partially-out bits.
q2 = [0.5, 0.5, -0.5, 0.5]
body3 = (bytes([3]) + bx_valid(1, [1, 0, 0, 0], [10, 20, -1800], 0.25, 0x31, 0x14D)
         + bx_missing(2, 0x31, 0x14D) + bytes([3, 4]) + struct.pack("<H", 0x0040))
body_oov = (bytes([2]) + bx_valid(1, q2, [415.95, -570.8, -1901.9], 0.2477, 0x71, 77)
            + bx_valid(2, [0, 1, 0, 0], [-5, 6, -900], 0.5, 0xB1, 77) + struct.pack("<H", 0))
cases["bx_three_tools_and_volume_bits"] = {
    "source": "bytes built from fact sheet §6.3/§6.4 layouts",
    "chunks": [H(binary_reply(body3)), H(binary_reply(body_oov))],
    "expect": [
        {"kind": "bx", "options": "0801", "system_status": 0x40,
         "tools": [tool(1, "ok", [1, 0, 0, 0], [10, 20, -1800], 0.25, 0x31, 0x14D), tool(2, "missing", port=0x31, frame=0x14D),
                   tool(3, "disabled")]},
        {"kind": "bx", "options": "0801", "system_status": 0,
         "tools": [dict(tool(1, "ok", q2, [415.95, -570.8, -1901.9], 0.2477, 0x71, 77), out_of_volume=True, partially_out=False),
                   dict(tool(2, "ok", [0, 1, 0, 0], [-5, 6, -900], 0.5, 0xB1, 77), out_of_volume=False, partially_out=True)]},
    ],
    "counters": {"replies": 2, "crc_errors": 0}}

# 3. Split at every awkward place: one byte at a time.
frame = binary_reply(body3)
cases["bx_byte_by_byte"] = {
    "source": "as 2, fed one byte per chunk",
    "chunks": [H(frame[i:i + 1]) for i in range(len(frame))],
    "expect": [cases["bx_three_tools_and_volume_bits"]["expect"][0]],
    "counters": {"replies": 1, "crc_errors": 0, "resyncs": 0}}

# 4. Corruption: flipped bit in the body, in the header; garbage; truncated reply; then good ones.
good = binary_reply(body3)
flip_body = bytearray(good); flip_body[20] ^= 0x08
flip_hdr = bytearray(good); flip_hdr[2] ^= 0x01
trunc = good[:30]
cases["bx_corruption_then_good"] = {
    "source": "as 2 with bits flipped, truncated, and garbage in front",
    "chunks": [H(bytes(flip_body)), H(good), H(bytes(flip_hdr)), H(b"\x00\xff\x13garbage\x7f\xc4\x00"), H(good),
               H(trunc), H(ascii_reply("OKAY"))],
    "expect": [cases["bx_three_tools_and_volume_bits"]["expect"][0], cases["bx_three_tools_and_volume_bits"]["expect"][0]],
    "counters": {"replies": 2, "min_crc_errors": 2, "min_resyncs": 2},
    "note": "the truncated reply swallows the OKAY that follows: nothing corrupt may come out, and the decoder waits"}

# 5. ASCII replies: OKAY, ERROR, WARNING, RESET, PHSR lists (CRCs from the fact sheet table).
cases["ascii_status_replies"] = {
    "source": "fact sheet §2.4 test vectors and §3",
    "chunks": ["4f4b4159413839360d", H(b"ERROR016BC2\r"), H(b"ERROR0C4E42\r"), H(b"WARNING02C28C\r"), H(b"RESETBE6F\r"),
               H(b"001414\r"), H(b"010A001C1B5\r"), H(b"040A01F0B01F0C01F0D01F2DDB\r"), H(b"Testing!A81C\r"), H(b"1D4C1\r")],
    "expect": [
        {"kind": "ascii", "text": "OKAY", "status": "okay"},
        {"kind": "ascii", "text": "ERROR01", "status": "error", "code": 1},
        {"kind": "ascii", "text": "ERROR0C", "status": "error", "code": 12},
        {"kind": "ascii", "text": "WARNING02", "status": "warning", "code": 2},
        {"kind": "ascii", "text": "RESET", "status": "reset"},
        {"kind": "phsr", "handles": []},
        {"kind": "phsr", "handles": [[10, 1]]},
        {"kind": "phsr", "handles": [[10, 0x1F], [11, 0x1F], [12, 0x1F], [13, 0x1F]]},
        {"kind": "ascii", "text": "Testing!", "status": "data"},
        {"kind": "ascii", "text": "1", "status": "data"},
    ],
    "counters": {"replies": 10, "crc_errors": 0, "resyncs": 0}}

# 6. ASCII corruption: bad CRC, garbage glued in front, truncated reply in front, LF inside.
ver = "Polaris Vicra Control Firmware\nFreeze Tag: Polaris Vicra Rev 007\nCombined Firmware Revision: 015"
cases["ascii_corruption"] = {
    "source": "fact sheet §2.2 recipe; corruptions of §9.3",
    "chunks": [H(b"OKAYA897\r"), H(b"\x00\x81xyOKAYA896\r"), H(b"ERR"), H(b"ERROR0C4E42\r"), H(ascii_reply(ver)),
               H(b"OK\r"), H(b"\xc4\xa5\x02"), H(ascii_reply("OKAY"))],
    "expect": [
        {"kind": "ascii", "text": "OKAY", "status": "okay"},
        {"kind": "ascii", "text": "ERROR0C", "status": "error", "code": 12},
        {"kind": "ascii", "text": ver, "status": "data"},
        {"kind": "ascii", "text": "OKAY", "status": "okay"},
    ],
    "counters": {"replies": 4, "min_crc_errors": 1, "min_resyncs": 3}}

# 7. TX text replies (option 0801): a real capture's handle line (§6.2), MISSING, DISABLED, UNOCCUPIED.
tx = ("03" "01+07082-04513-01855-05101+041595-057080-190190+02477000000310000014D\n"
      "02MISSING000000310000014D\n" "03DISABLED000000000000014D\n" "0000")
tx2 = "0201+10000+00000+00000+00000+000000+000000-150000+0000000000031000003E8\n04UNOCCUPIED\n0081"
cases["tx_replies"] = {
    "source": "fact sheet §6.2 (real capture's handle 01 values)",
    "chunks": [H(ascii_reply(tx)), H(ascii_reply(tx2))],
    "expect": [
        {"kind": "tx", "options": "0801", "system_status": 0,
         "tools": [tool(1, "ok", [0.7082, -0.4513, -0.1855, -0.5101], [415.95, -570.80, -1901.90], 0.2477, 0x31, 0x14D, text=True),
                   tool(2, "missing", port=0x31, frame=0x14D), tool(3, "disabled", port=0, frame=0x14D)],
         "exact": True},
        {"kind": "tx", "options": "0801", "system_status": 0x81,
         "tools": [tool(1, "ok", [1, 0, 0, 0], [0, 0, -1500], 0.0, 0x31, 1000, text=True), tool(4, "unoccupied")], "exact": True},
    ],
    "counters": {"replies": 2, "crc_errors": 0}}

# 8. Well-framed but inconsistent content: must be a ProtocolError, not a frame.
bad_len = bytes([2]) + bx_valid(1, [1, 0, 0, 0], [0, 0, 0], 0.1, 0x31, 5) + struct.pack("<H", 0)  # says 2 handles, has 1
bad_status = bytes([1, 1, 9]) + struct.pack("<H", 0)
bad_quat = bytes([1]) + bx_valid(1, [2, 0, 0, 0], [0, 0, 0], 0.1, 0x31, 5) + struct.pack("<H", 0)
nan_t = bytes([1]) + bx_valid(1, [1, 0, 0, 0], [float("nan"), 0, 0], 0.1, 0x31, 5) + struct.pack("<H", 0)
trailing = body3 + b"\x00"
cases["bx_protocol_errors"] = {
    "source": "well-framed replies whose content breaks §6.3",
    "chunks": [H(binary_reply(b)) for b in (bad_len, bad_status, bad_quat, nan_t, trailing)],
    "expect": [{"kind": "bx", "options": "0801", "protocol_error": True}] * 5,
    "counters": {"replies": 5, "crc_errors": 0}}

out = os.path.join(os.path.dirname(os.path.abspath(__file__)), "codec")
os.makedirs(out, exist_ok=True)
for name, c in cases.items():
    with open(os.path.join(out, name + ".json"), "w") as f:
        json.dump(c, f, indent=1)
        f.write("\n")

# Command encoding vectors: the fact sheet's table (§2.4), the wire form with CR.
cmds = [("INIT", ""), ("VER", "0"), ("APIREV", ""), ("COMM", "50000"), ("COMM", "00000"), ("COMM", "70000"),
        ("PHSR", "00"), ("PHSR", "01"), ("PHSR", "02"), ("PHSR", "03"), ("PHSR", "04"), ("PHRQ", "*********1****"),
        ("PINIT", "01"), ("PENA", "01D"), ("PHF", "01"), ("TSTART", ""), ("TSTART", "80"), ("TSTOP", ""),
        ("TX", "0001"), ("TX", "0801"), ("BX", "0001"), ("BX", "0801"), ("BX", "1801"), ("BEEP", "1"), ("PHINF", "010001"),
        ("GETINFO", "Features.Firmware.Version")]
spec_crc = {"INIT:": "E3A5", "VER:0": "65EE", "APIREV:": "443E", "COMM:50000": "0048", "COMM:00000": "0084",
            "COMM:70000": "C031", "PHSR:00": "20FF", "PHSR:01": "E03E", "PHSR:02": "E17E", "PHSR:03": "21BF",
            "PHSR:04": "E3FE", "PHRQ:*********1****": "A4C1", "PINIT:01": "31EA", "PENA:01D": "6D3B", "PHF:01": "CF0C",
            "TSTART:": "5423", "TSTART:80": "1B0B", "TSTOP:": "2C14", "TX:0001": "031A", "TX:0801": "C19B",
            "BX:0001": "C26D", "BX:0801": "00EC", "BX:1801": "FCED", "BEEP:1": "8404", "PHINF:010001": "CFAC",
            "GETINFO:Features.Firmware.Version": "0492"}
vec = []
for n, p in cmds:
    s = f"{n}:{p}"
    assert "%04X" % crc16(s.encode()) == spec_crc[s], s
    vec.append({"name": n, "params": p, "wire": s + spec_crc[s] + "\r"})
with open(os.path.join(out, "commands.json"), "w") as f:
    json.dump({"source": "fact sheet §2.4 (CRCs checked against the table)", "commands": vec}, f, indent=1)
    f.write("\n")
