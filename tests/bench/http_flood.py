#!/usr/bin/env python3
"""Lease success under a flood of unauthenticated connections. A benchmark, not a test: it prints
figures and fails only when it cannot run.

A fresh collector (default limits: 256 connections) on a temporary state directory; FLOOD
connections that never authenticate, reopened as soon as the collector closes them: a third idle,
a third slowloris (a header byte every few seconds), a third sending GET /healthz on a keep-alive
connection every 20 s. Meanwhile LEASES lease requests with the token, one connection each as the
worker makes them, each allowed TIMEOUT seconds; it prints how many were answered 200 (a lease or
a retry_after_ms: the collector served the worker) and how the others failed.

Usage, after the README's build:  tests/bench/http_flood.py
Environment: DTRACED (default build/src/cli/dtraced), FLOOD (600), LEASES (80), TIMEOUT (5),
KEEP_LOGS=1 to keep the temporary directory.
"""
import http.client
import os
import re
import selectors
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DTRACED = os.environ.get("DTRACED", os.path.join(ROOT, "build/src/cli/dtraced"))
FLOOD = int(os.environ.get("FLOOD", "600"))
LEASES = int(os.environ.get("LEASES", "80"))
TIMEOUT = float(os.environ.get("TIMEOUT", "5"))
TOKEN = "flood-bench-token"


def pixel_version():
    """The pixel version the collector wants on leases, as `dtraced --version` prints it."""
    out = subprocess.run([DTRACED, "--version"], capture_output=True, text=True, check=True).stdout
    found = re.search(r"pixel version (\d+)", out)
    if not found:
        sys.exit(f"http_flood: no pixel version in `{DTRACED} --version`: {out.strip()}")
    return found.group(1)


def start_collector(work):
    token_file = os.path.join(work, "token")
    with open(token_file, "w") as f:
        f.write(TOKEN + "\n")
    os.chmod(token_file, 0o600)
    log = open(os.path.join(work, "collector.log"), "w")
    proc = subprocess.Popen([DTRACED, "--role", "collector", "--listen", "127.0.0.1:0", "--state-dir",
                             os.path.join(work, "state"), "--token-file", token_file], stderr=log)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        with open(os.path.join(work, "collector.log")) as f:
            m = re.search(r"listening on .* port (\d+)", f.read())
        if m:
            return proc, int(m.group(1))
        if proc.poll() is not None:
            break
        time.sleep(0.1)
    proc.kill()
    sys.exit("the collector did not start; see " + os.path.join(work, "collector.log"))


class Flood:
    """FLOOD unauthenticated connections, each reopened when the collector closes it."""

    def __init__(self, port):
        self.port = port
        self.stop = threading.Event()
        self.reopened = 0
        self.thread = threading.Thread(target=self.run, daemon=True)

    def open(self, kind):
        s = socket.socket()
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", self.port))
        return {"sock": s, "kind": kind, "next": time.monotonic() + 0.5, "sent": False}

    def run(self):
        sel = selectors.DefaultSelector()
        conns = [self.open(("idle", "slowloris", "healthz")[i % 3]) for i in range(FLOOD)]
        for c in conns:
            sel.register(c["sock"], selectors.EVENT_READ, c)
        while not self.stop.is_set():
            for key, _ in sel.select(timeout=0.2):
                c = key.data
                try:
                    data = c["sock"].recv(65536)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    data = b""
                if not data:  # closed by the collector: reopen at once, as an attacker would
                    sel.unregister(c["sock"])
                    c["sock"].close()
                    fresh = self.open(c["kind"])
                    c.update(fresh)
                    sel.register(c["sock"], selectors.EVENT_READ, c)
                    self.reopened += 1
            now = time.monotonic()
            for c in conns:
                if now < c["next"]:
                    continue
                try:
                    if c["kind"] == "slowloris":
                        c["sock"].send(b"GET /healthz HTTP/1.1\r\nHost: x\r\n" if not c["sent"] else b"X: y\r\n")
                        c["next"] = now + 3
                    elif c["kind"] == "healthz":
                        c["sock"].send(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
                        c["next"] = now + 20
                    else:
                        c["next"] = now + 3600
                    c["sent"] = True
                except OSError:
                    c["next"] = now + 1
        for c in conns:
            c["sock"].close()


def lease(port, version):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=TIMEOUT)
    try:
        conn.request("POST", "/v1/lease", body=b'{"worker": "bench", "threads": 1}',
                     headers={"Authorization": "Bearer " + TOKEN, "Content-Type": "application/json",
                              "X-Dtraced-Pixel-Version": version})
        return str(conn.getresponse().status)
    except socket.timeout:
        return "timeout"
    except OSError as e:
        return type(e).__name__
    finally:
        conn.close()


def main():
    if not os.access(DTRACED, os.X_OK):
        sys.exit(f"not found: {DTRACED} (build first, or set DTRACED)")
    version = pixel_version()
    work = tempfile.mkdtemp(prefix="dtraced-flood-")
    proc, port = start_collector(work)
    flood = Flood(port)
    try:
        flood.thread.start()
        time.sleep(3)  # the flood is in place
        outcomes = {}
        for _ in range(LEASES):
            result = lease(port, version)
            outcomes[result] = outcomes.get(result, 0) + 1
        served = outcomes.get("200", 0)
        print(f"flood: {FLOOD} unauthenticated connections (idle, slowloris, /healthz keep-alive), "
              f"{flood.reopened} reopened after the collector closed them")
        print(f"leases answered 200: {served} of {LEASES} ({100.0 * served / LEASES:.0f} %)")
        print("outcomes: " + ", ".join(f"{k}: {v}" for k, v in sorted(outcomes.items())))
    finally:
        flood.stop.set()
        flood.thread.join(timeout=10)
        proc.terminate()
        proc.wait(timeout=30)
        if os.environ.get("KEEP_LOGS") == "1":
            print("logs kept in " + work)
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
