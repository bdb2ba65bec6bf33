"""Writes the golden vectors of `tecdar-imu/1` (*.vec): each packet's contents and its bytes. Both ends test
against these files: the firmware's encoder must produce the bytes, the daemon's parser must decode the
contents. The bytes are checked here with a bitwise CRC written from the spec's parameters, not with the
encoders under test. Run once; the files are the reference (python3 firmware/vectors/make_vectors.py)."""
import pathlib
import random
import struct

HERE = pathlib.Path(__file__).parent


def crc_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE from its definition: poly 0x1021, init 0xFFFF, no reflection, xorout 0."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


assert crc_bitwise(b"123456789") == 0x29B1


def frame(ptype: int, payload: bytes) -> bytes:
    body = struct.pack("<BH", ptype, len(payload)) + payload
    return b"\xa5\x5a" + body + struct.pack("<H", crc_bitwise(body))


def samples(seq, t0_us, rows):
    payload = struct.pack("<HIB", seq, t0_us, len(rows)) + b"".join(struct.pack("<6h", *r) for r in rows)
    lines = [f"samples seq={seq} t0_us={t0_us} n={len(rows)}"] + ["sample " + " ".join(map(str, r)) for r in rows]
    return lines, frame(0x01, payload)


def status(odr, gfs, afs, flags):
    return ([f"status odr_hz={odr} gyro_fs_dps={gfs} accel_fs_g={afs} flags={flags}"],
            frame(0x02, struct.pack("<HHBB", odr, gfs, afs, flags)))


def identity(who_am_i):
    return [f"identity who_am_i={who_am_i}"], frame(0x03, bytes([who_am_i]))


def unknown(ptype, payload):
    return [f"frame type={ptype} payload={payload.hex()}"], frame(ptype, payload)


def write(name, title, entries):
    out = [f"# {title}", "# one packet per entry: its contents, then its bytes (hex); the stream is the bytes in order"]
    for lines, raw in entries:
        out += lines + ["bytes " + raw.hex()]
    (HERE / f"{name}.vec").write_text("\n".join(out) + "\n")


def rows(rng, n, extremes=False):
    r = [[rng.randint(-32768, 32767) for _ in range(6)] for _ in range(n)]
    if extremes:
        r[0] = [-32768, 32767, 0, -1, 1, 32767]
        r[-1] = [32767, -32768, -1, 0, -32768, 1]
    return r


def main():
    rng = random.Random(20261203)
    write("status", "a status with each full scale and each flag", [
        status(6667, 125, 2, 0), status(6667, 250, 4, 1), status(6667, 500, 8, 2), status(6667, 1000, 16, 4),
        status(6667, 2000, 2, 3), status(6667, 4000, 16, 7), status(3333, 4000, 4, 0), status(12, 250, 8, 0)])
    write("seq_and_time_wrap", "seq wraps at 65536 and t0_us at 2^32 in the same stream (8 samples a packet)", [
        samples(65534, 4294965896, rows(rng, 8)), samples(65535, 4294967096, rows(rng, 8)),
        samples(0, 1000, rows(rng, 8)), samples(1, 2200, rows(rng, 8))])
    write("sizes", "n = 1 and n = 64 (the largest packet), with the int16 extremes", [
        samples(7, 0, rows(rng, 1, True)), samples(8, 150, rows(rng, 64, True)), samples(9, 9750, rows(rng, 1))])
    write("unknown_types", "frames of types the protocol does not define, skipped by their len, between samples", [
        samples(100, 5000, rows(rng, 2)), unknown(0x00, b""), unknown(0x04, bytes([1, 2, 3, 4])),
        samples(101, 5300, rows(rng, 2)), unknown(0x7E, bytes(range(256)) * 4), unknown(0xFF, b"\xa5\x5a\x01"),
        status(6667, 4000, 16, 0), samples(102, 5600, rows(rng, 2))])
    write("identity", "our extension (type 0x03): the sensor's WHO_AM_I after each status, for either part and none",
          [status(6667, 4000, 16, 0), identity(0x6B), status(6667, 2000, 16, 0), identity(0x6C),
           status(6667, 4000, 16, 4), identity(0xFF)])


if __name__ == "__main__":
    main()
