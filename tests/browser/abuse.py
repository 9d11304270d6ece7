"""The `play` server under hostile clients, on the loopback, bounded in count and time (about a
minute): raw sockets and a small WebSocket client written here, the standard library alone.

    python3 tests/browser/abuse.py target/release/examples/play [--report-only]

One well-behaved drive runs throughout (it holds the up arrow and counts the dream's frames) while
each case in turn: oversized and malformed WebSocket messages, too many drives, slowloris and idle
connections, a flood of pending connections, bad HTTP heads. For each case it prints the server's
peak RSS and CPU, and the good drive's frames per second. Then it asserts (unless --report-only,
which prints the table of an older server as it is): the server's RSS stays under RSS_LIMIT_MIB,
the good drive keeps >= 20 fps, every bad client gets its plain answer, the server's log stays
short, and afterwards it still serves a page and a drive.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time

RSS_LIMIT_MIB = 256  # the server alone is about 60 MiB, each drive a few more
FPS_MIN = 20.0
CASE_SECONDS = 3.0
EXTRA_DRIVES = 16  # past the server's limit: 20 drives in all at its default of 4 (2 cores)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def connect(port: int, timeout: float = 5.0) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=timeout)


def read_until_closed(s: socket.socket, limit: int = 1 << 20) -> tuple[bytes, str]:
    """What the server sent until it closed, and how it closed: "fin", "reset" or "timeout"."""
    data = b""
    try:
        while len(data) < limit:
            chunk = s.recv(65536)
            if not chunk:
                return data, "fin"
            data += chunk
    except ConnectionResetError:
        return data, "reset"
    except socket.timeout:
        return data, "timeout"
    return data, "too much"


def http(port: int, raw: bytes) -> tuple[str, str]:
    """The status line the server answers to `raw`, and how it closed."""
    with connect(port) as s:
        try:
            s.sendall(raw)
        except (BrokenPipeError, ConnectionResetError):
            pass
        data, how = read_until_closed(s)
    return data.split(b"\r\n", 1)[0].decode(errors="replace"), how


class WebSocket:
    """A client end: the handshake, masked frames out, frames in."""

    def __init__(self, port: int, timeout: float = 5.0):
        self.sock = connect(port, timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                raise ConnectionError("closed during the handshake")
            head += chunk
        if not head.startswith(b"HTTP/1.1 101"):
            raise ConnectionError(head.split(b"\r\n", 1)[0].decode(errors="replace"))

    def send(self, payload: bytes, opcode: int = 1, fin: bool = True) -> None:
        n = len(payload)
        size = bytes([0x80 | n]) if n < 126 else (bytes([0x80 | 126]) + struct.pack(">H", n) if n < 65536
                                                  else bytes([0x80 | 127]) + struct.pack(">Q", n))
        # A big payload goes with the all-zero masking key (legal, and the payload is then sent as
        # it is): masking megabytes byte by byte in Python would take seconds.
        mask = os.urandom(4) if n < 4096 else bytes(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload)) if n < 4096 else payload
        self.sock.sendall(bytes([(0x80 if fin else 0) | opcode]) + size + mask + masked)

    def recv(self) -> tuple[int, bytes]:
        def exactly(n):
            data = b""
            while len(data) < n:
                chunk = self.sock.recv(n - len(data))
                if not chunk:
                    raise ConnectionError("closed")
                data += chunk
            return data
        b0, b1 = exactly(2)
        n = b1 & 0x7F
        n = struct.unpack(">H", exactly(2))[0] if n == 126 else struct.unpack(">Q", exactly(8))[0] if n == 127 else n
        return b0 & 0x0F, exactly(n)

    def close(self) -> None:
        """Gone at once: a shutdown wakes a reader blocked on the socket in another thread."""
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class Drive(threading.Thread):
    """A well-behaved drive: holds the up arrow, reads every frame, keeps their arrival times."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.ws, self.times, self.stop, self.error = WebSocket(port), [], False, None
        self.hello = json.loads(self.ws.recv()[1])
        self.ws.send(b"keys 0 1")
        self.sampling = None

    def run(self):
        try:
            while not self.stop:
                opcode, payload = self.ws.recv()
                if opcode == 2 and payload[0] == 1:
                    self.times.append(time.monotonic())
                    self.sampling = payload[10]
                elif opcode == 8:
                    raise ConnectionError(f"closed by the server: {payload[2:].decode(errors='replace')}")
        except Exception as e:  # noqa: BLE001 -- reported by the case that saw it
            self.error = e if not self.stop else None

    def fps(self, since: float) -> float:
        """Frames a second since `since`, over at least the last second."""
        since = min(since, time.monotonic() - 1.0)
        n = sum(1 for t in self.times if t >= since)
        return n / (time.monotonic() - since)

    def finish(self) -> None:
        """Closes the drive as a page does (a close frame), and waits for the reader."""
        self.stop = True
        try:
            self.ws.send(struct.pack(">H", 1000), opcode=8)
        except OSError:
            pass
        self.join(2)
        self.ws.close()


class Server:
    def __init__(self, binary: str, log: str):
        self.port, self.log = free_port(), log
        self.proc = subprocess.Popen([binary, "--port", str(self.port)], stdout=subprocess.PIPE,
                                     stderr=open(log, "wb"), text=True)
        line = self.proc.stdout.readline()
        self.max_drives = int(line.split("at most ")[1].split()[0]) if "at most" in line else None
        for _ in range(600):
            try:
                connect(self.port).close()
                return
            except OSError:
                time.sleep(0.1)
        raise RuntimeError("the server did not listen")

    def status(self, field: str) -> int:
        with open(f"/proc/{self.proc.pid}/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith(field + ":"))

    def cpu_seconds(self) -> float:
        with open(f"/proc/{self.proc.pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def oversized(port, out):
    """Three clients each send a 64 MiB text message in four 16 MiB fragments (each within the
    WebSocket library's default frame limit); one sends one 16 MiB message of control bytes (a
    malformed message whose log line could be as long); one sends 300 bytes in 30-byte fragments."""
    def one(fragments):
        try:
            ws = WebSocket(port, timeout=30)
            ws.recv()
            for i in range(fragments):
                ws.send(b"\x01" * (16 << 20), opcode=1 if i == 0 else 0, fin=i == fragments - 1)
            out.append(read_until_closed(ws.sock, 64 << 20)[1])
        except OSError as e:
            out.append(type(e).__name__)
    threads = [threading.Thread(target=one, args=(n,)) for n in (4, 4, 4, 1)]
    [t.start() for t in threads]
    ws = WebSocket(port)
    ws.recv()
    for i in range(10):
        ws.send(b"k" * 30, opcode=1 if i == 0 else 0, fin=i == 9)
    [t.join(60) for t in threads]
    out.append(read_until_closed(ws.sock, 1 << 20)[1])


def malformed(port, out):
    """Twenty clients each send a 200-byte message of control bytes, then one of NaN keys."""
    for payload in [b"\x01" * 200] * 20 + [b"keys NaN 1e309"]:
        ws = WebSocket(port)
        ws.recv()
        ws.send(payload)
        out.append(read_until_closed(ws.sock, 8 << 20)[1])


def too_many_drives(port, out, max_drives):
    """max_drives + EXTRA_DRIVES more drives: those past the limit must be told, the rest drive."""
    drives, refused = [], []
    for _ in range(max_drives + EXTRA_DRIVES):
        ws = WebSocket(port)
        opcode, payload = ws.recv()
        if opcode == 8:
            refused.append((struct.unpack(">H", payload[:2])[0], payload[2:].decode(errors="replace")))
            ws.send(payload[:2], opcode=8)
            ws.close()
        else:
            drives.append(ws)
            threading.Thread(target=_read_all, args=(ws,), daemon=True).start()
    time.sleep(CASE_SECONDS)
    out.append({"driving": len(drives), "refused": refused})
    for ws in drives:
        ws.close()


def _read_all(ws: WebSocket) -> None:
    try:
        while True:
            ws.recv()
    except OSError:  # closed by the case
        pass


def slow_and_idle(port, out):
    """Forty idle connections and forty that send a request head a byte every half second."""
    idle = [connect(port) for _ in range(40)]
    slow = [connect(port) for _ in range(40)]
    end = time.monotonic() + CASE_SECONDS
    while time.monotonic() < end:
        for s in slow:
            try:
                s.send(b"G")
            except OSError:
                pass
        time.sleep(0.5)
    half = connect(port)
    half.shutdown(socket.SHUT_WR)  # a half-closed client must be let go at once
    out.append(read_until_closed(half)[1])
    for s in idle + slow + [half]:
        s.close()


def pending_flood(port, out):
    """Three hundred connections that say nothing: past the server's pending limit, a 503."""
    socks = [connect(port) for _ in range(300)]
    time.sleep(0.5)
    for s in socks[-20:]:
        s.settimeout(2)
        out.append(http_status(read_until_closed(s)[0]))
    for s in socks:
        s.close()


def http_status(data: bytes) -> str:
    return data.split(b"\r\n", 1)[0].decode(errors="replace")


def bad_http(port, out):
    out.append(("page", *http(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")))
    out.append(("9 KiB head", *http(port, b"GET / HTTP/1.1\r\nX: " + b"a" * 9000 + b"\r\n\r\n")))
    out.append(("garbage", *http(port, b"\x16\x03\x01\x02\x00 hello\r\n\r\n")))
    out.append(("traversal", *http(port, b"GET /../../etc/passwd HTTP/1.1\r\n\r\n")))
    out.append(("POST", *http(port, b"POST / HTTP/1.1\r\nContent-Length: 0\r\n\r\n")))


def close_answered(port, out):
    ws = WebSocket(port)
    ws.recv()
    ws.send(struct.pack(">H", 1000), opcode=8)
    try:
        while True:
            opcode, payload = ws.recv()
            if opcode == 8:
                out.append(struct.unpack(">H", payload[:2])[0] if payload else "empty")
                break
    except (ConnectionError, socket.timeout) as e:
        out.append(type(e).__name__)
    ws.close()


def sample_presses(port, out):
    """Two presses of `sample` in one tick leave sampling off; three turn it on."""
    drive = Drive(port)
    drive.start()
    if not drive.hello.get("samples"):
        out.append("the model does not sample")
    else:
        for presses in (2, 3):
            drive.ws.sock.sendall(b"".join(_frame(b"sample") for _ in range(presses)))
            time.sleep(0.5)
            out.append((presses, drive.sampling))
    drive.finish()


def _frame(payload: bytes) -> bytes:
    mask = os.urandom(4)
    return bytes([0x81, 0x80 | len(payload)]) + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("play", help="the built examples/play binary")
    p.add_argument("--report-only", action="store_true", help="print the table, assert nothing (an older server)")
    a = p.parse_args()
    log = tempfile.NamedTemporaryFile(prefix="play-abuse-", suffix=".log", delete=False).name
    server = Server(a.play, log)
    max_drives = server.max_drives or 4
    rows, failures = [], []
    try:
        good = Drive(server.port)
        good.start()
        time.sleep(1.0)
        cases = [("the good drive alone", lambda out: time.sleep(CASE_SECONDS)),
                 ("3 x 64 MiB, 16 MiB, 300 B messages", lambda out: oversized(server.port, out)),
                 ("21 malformed messages", lambda out: malformed(server.port, out)),
                 (f"{max_drives + EXTRA_DRIVES} more drives", lambda out: too_many_drives(server.port, out, max_drives)),
                 ("40 idle + 40 slowloris", lambda out: slow_and_idle(server.port, out)),
                 ("300 silent connections", lambda out: pending_flood(server.port, out)),
                 ("bad HTTP", lambda out: bad_http(server.port, out)),
                 ("a client's close", lambda out: close_answered(server.port, out)),
                 ("sample pressed 2 and 3 times", lambda out: sample_presses(server.port, out))]
        for name, case in cases:
            out, start, cpu = [], time.monotonic(), server.cpu_seconds()
            thread = threading.Thread(target=lambda: _guard(case, out), daemon=True)
            thread.start()
            peak = server.status("VmRSS")
            while thread.is_alive() and time.monotonic() - start < 60:
                peak = max(peak, server.status("VmRSS"))
                thread.join(0.05)
            peak = max(peak, server.status("VmRSS"))
            elapsed = time.monotonic() - start
            fps = good.fps(start)
            cpu_share = (server.cpu_seconds() - cpu) / elapsed  # in clock ticks: noise under a second
            rows.append((name, peak / 1024, fps, cpu_share, out))
            cpu_text = f"{cpu_share:4.2f}" if elapsed >= 1 else "   -"
            print(f"{name:36s} RSS {peak / 1024:7.1f} MiB  good drive {fps:5.1f} fps  server CPU {cpu_text} core  "
                  f"({elapsed:.1f} s)  {out}", flush=True)
            if fps < FPS_MIN:
                failures.append(f"{name}: the good drive at {fps:.1f} fps")
            if good.error:
                failures.append(f"{name}: the good drive ended: {good.error}")
                break
        results = {name: out for name, _, _, _, out in rows}
        drives = (results.get(f"{max_drives + EXTRA_DRIVES} more drives") or [{}])[0]
        drives = drives if isinstance(drives, dict) else {}
        time.sleep(0.5)  # the cases' drives given back
        after_page = http(server.port, b"GET / HTTP/1.1\r\n\r\n")
        after = Drive(server.port)
        after.start()
        time.sleep(1.5)
        after_fps = after.fps(time.monotonic())
        after.finish()
        print(f"afterwards: page {after_page}, a new drive at {after_fps:.1f} fps")
        peak_all = server.status("VmHWM") / 1024
        log_size = os.path.getsize(log)
        print(f"server: peak RSS {peak_all:.1f} MiB over the whole run (limit {RSS_LIMIT_MIB}); log {log_size} bytes")
        checks = [
            (peak_all < RSS_LIMIT_MIB, f"peak RSS {peak_all:.1f} MiB"),
            (log_size < 64 << 10, f"the log grew to {log_size} bytes"),
            (after_page[0].startswith("HTTP/1.1 200") and after_page[1] == "fin", f"afterwards: {after_page}"),
            (after_fps >= FPS_MIN, f"afterwards: a new drive at {after_fps:.1f} fps"),
            # The good drive holds one place: max_drives - 1 more drive, the rest are told why.
            (drives.get("driving") == max_drives - 1 and len(drives.get("refused", [])) == EXTRA_DRIVES + 1
             and all(code == 1013 and "busy" in why for code, why in drives["refused"]), f"the drives past the limit: {drives}"),
            (results.get("40 idle + 40 slowloris", []) == ["fin"], "a half-closed client not let go"),
            (all(s.startswith("HTTP/1.1 503") for s in results.get("300 silent connections", [""])), "the flood's 503"),
            ([(n, s.split(" ")[1] if " " in s else s, how) for n, s, how in results.get("bad HTTP", [])] ==
             [("page", "200", "fin"), ("9 KiB head", "431", "fin"), ("garbage", "400", "fin"),
              ("traversal", "404", "fin"), ("POST", "405", "fin")], "the HTTP answers"),
            (results.get("a client's close") == [1000], "the client's close not answered"),
            (results.get("sample pressed 2 and 3 times") in (["the model does not sample"], [(2, 0), (3, 1)]),
             "sample presses within one tick"),
        ]
        failures += [what for ok, what in checks if not ok]
    finally:
        server.proc.terminate()
        server.proc.wait(10)
    with open(log, "rb") as f:
        tail = f.read()[-600:].decode(errors="replace")
    print(f"the server's log ends: {tail!r}")
    os.unlink(log)
    if failures and not a.report_only:
        print("FAILED: " + "; ".join(failures), file=sys.stderr)
        return 1
    print("the play server under abuse: " + ("ok" if not failures else "report only: " + "; ".join(failures)))
    return 0


def _guard(case, out):
    try:
        case(out)
    except Exception as e:  # noqa: BLE001 -- a case the server broke shows in its row
        out.append(f"{type(e).__name__}: {e}")


if __name__ == "__main__":
    sys.exit(main())
