#!/usr/bin/env python3
"""The tail of a farm job: how long the last 10 % of its tiles take (issue 16, "Farm").

A job whose cost is uneven (one region of glass in an otherwise cheap image) ends with a few
expensive tiles rendering while the rest of the farm has nothing left to do. This benchmark
starts a collector and WORKERS workers (one render thread each) on 127.0.0.1, submits a scene
with one expensive region (a cluster of glass spheres in the lower right, the part of the image
leased last in the collector's row order; `--glass top` turns the camera upside down, so that the
same cluster is in the first rows), and
polls the job's progress (GET /v1/jobs/ID, Boost.JSON on the collector's side, Python's json
here) every POLL seconds. It prints, per tile size:

  - tiles, the job's time from submission to the last stored tile;
  - "last 10 %": the time from the moment 90 % of the tiles were stored to the last one, and
    that time's share of the job (ideal: the last 10 % of the work takes about 10 % of the time,
    when every tile costs the same);
  - the same for the last 1 %;
  - "workers busy": the workers' CPU time over the job (utime + stime from /proc) divided by
    workers x job time: what the tail leaves idle shows here (on a shared machine other work
    lowers it too; compare the rows of one run).

Where the expensive tiles are leased last, the last 10 % of the tiles take more than 10 % of
the job; leased first (`--glass top`), less.

`--order` says how the collector leases: "row" submits with `--no-cost-pass` (row order), "cost"
as `dtraced submit` does by default (a low-resolution pre-pass estimates each tile's cost, and
the collector leases the costliest first), "both" (the default) alternates the two, run by run,
so that both rows of a tile size come from the same minutes of a shared machine. The job's time
runs from the start of `dtraced submit` (so it includes the pre-pass; "submit s" shows that part
alone). For the cost order the benchmark prints a target line per tile size: the last 10 % of
the tiles take at most 10 % of the job, MET or MISSED (medians).

A benchmark, not a test: figures only; it fails only when it cannot run.

Usage: tests/bench/job_tail.py [--dtraced build/src/cli/dtraced] [--workers 2] [--tiles 16,32,64]
       [--runs 3] [--glass bottom|top] [--order both|row|cost] [--samples 2] [--keep]
"""

import argparse
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))

parser = argparse.ArgumentParser(description="the last 10 % of a farm job's tiles")
parser.add_argument("--dtraced", default=os.path.join(ROOT, "build", "src", "cli", "dtraced"))
parser.add_argument("--workers", type=int, default=2, help="workers, one render thread each")
parser.add_argument("--tiles", default="16,32,64", help="tile sizes to measure, comma-separated")
parser.add_argument("--runs", type=int, default=3, help="runs per tile size (medians printed)")
parser.add_argument("--glass", choices=["bottom", "top"], default="bottom",
                    help="where the expensive region is: leased last (bottom) or first (top)")
parser.add_argument("--order", choices=["both", "row", "cost"], default="both",
                    help="lease order: row (--no-cost-pass), cost (submit's pre-pass), or both alternating")
parser.add_argument("--width", type=int, default=640)
parser.add_argument("--height", type=int, default=360)
parser.add_argument("--samples", type=int, default=2)
parser.add_argument("--poll", type=float, default=0.02, help="seconds between progress polls")
parser.add_argument("--deadline", type=float, default=900, help="seconds a job may take at most")
parser.add_argument("--keep", action="store_true", help="keep the temporary directory")
args = parser.parse_args()


def scene(glass):
    """A cheap field of diffuse spheres on a plane and one cluster of glass spheres."""
    objects = [{"type": "plane", "loc": [0, 0, 0], "normal": [0, 1, 0],
                "material": {"color": [0.6, 0.6, 0.58], "diffuse": 1, "specular": 0.1, "shininess": 16}}]
    for i in range(7):
        for j in range(4):
            objects.append({"type": "sphere", "loc": [-4.5 + 1.5 * i, 0.4, -3.0 - 1.5 * j], "radius": 0.4,
                            "material": {"color": [0.2 + 0.1 * i, 0.3, 0.8 - 0.1 * j], "diffuse": 1,
                                         "specular": 0.3, "shininess": 32}})
    glass_material = {"color": [1, 1, 1], "diffuse": 0, "specular": 0.9, "shininess": 512,
                      "reflectivity": 0.1, "transparency": 0.9, "ior": 1.5}
    for i in range(4):
        for j in range(3):
            objects.append({"type": "sphere", "loc": [1.2 + 0.45 * i, 0.3 + 0.45 * (j % 2), 4.3 - 0.45 * j],
                            "radius": 0.3, "material": glass_material})
    return {
        # Upside down for --glass top: the same image turned by 180 degrees, the same cost.
        "camera": {"position": [0, 2.0, 7.5], "look_at": [0, 0.8, 0], "up": [0, 1 if glass == "bottom" else -1, 0],
                   "fov": 50},
        "render": {"width": args.width, "height": args.height, "samples": args.samples, "max_depth": 8,
                   "background": [0.55, 0.65, 0.8], "seed": 3},
        "scene_objects": objects,
        "scene_lights": [{"type": "point", "loc": [-4, 6, 5], "color": [1, 1, 1], "intensity": 300}],
    }


work = tempfile.mkdtemp(prefix="job-tail-")
procs = []


def stop_all():
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    if args.keep:
        print(f"logs kept in {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)


def fail(message):
    print(f"job_tail: {message}", file=sys.stderr)
    for name in sorted(os.listdir(work)):
        if name.endswith(".log"):
            with open(os.path.join(work, name)) as f:
                print(f"--- {name} (last 10 lines)", file=sys.stderr)
                print("".join(f.readlines()[-10:]), file=sys.stderr)
    stop_all()
    sys.exit(1)


def start_collector():
    token = os.path.join(work, "token")
    with open(token, "w") as f:
        f.write(f"tail-{os.getpid()}-token\n")
    log = open(os.path.join(work, "collector.log"), "w")
    p = subprocess.Popen([args.dtraced, "--role", "collector", "--listen", "127.0.0.1:0", "--state-dir",
                          os.path.join(work, "state"), "--token-file", token, "--tls", "off"],
                         stdout=subprocess.DEVNULL, stderr=log)
    procs.append(p)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        with open(os.path.join(work, "collector.log")) as f:
            m = re.findall(r"listening on .* port (\d+)", f.read())
        if m:
            return f"http://127.0.0.1:{m[-1]}", token
        if p.poll() is not None:
            break
        time.sleep(0.1)
    fail("the collector did not start")


def get_job(url, token, job):
    with open(token) as f:
        bearer = f.readline().strip()
    req = urllib.request.Request(f"{url}/v1/jobs/{job}", headers={"Authorization": f"Bearer {bearer}"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.load(r)


TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid):
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS  # utime, stime


def workers_cpu():
    return sum(cpu_seconds(p.pid) for p in procs[1:])


def run(url, token, scene_file, tile, index, order):
    cpu0 = workers_cpu()
    flags = ["--no-cost-pass"] if order == "row" else []
    t0 = time.monotonic()
    out = subprocess.run([args.dtraced, "submit", scene_file, "-o", f"tail-{tile}-{order}-{index}.png",
                          "--tile-size", str(tile), "--collector", url, "--token-file", token] + flags,
                         capture_output=True, text=True)
    submit_s = time.monotonic() - t0
    if out.returncode != 0:
        fail(f"submit failed: {out.stderr.strip()}")
    job = out.stdout.strip().split()[-1]
    times = []  # (seconds since submission, tiles stored)
    total = None
    while True:
        now = time.monotonic() - t0
        if now > args.deadline:
            fail(f"job {job} did not finish within {args.deadline} s")
        state = get_job(url, token, job)
        total = state["tiles_total"]
        times.append((now, state["tiles_done"]))
        if state["tiles_done"] >= total:
            break
        for p in procs:
            if p.poll() is not None:
                fail("a daemon exited")
        time.sleep(args.poll)

    def first_at(share):
        need = share * total
        return next(t for t, done in times if done >= need)

    job_s = times[-1][0]
    busy = (workers_cpu() - cpu0) / (args.workers * job_s)
    t90, t99 = first_at(0.9), first_at(0.99)
    return total, job_s, job_s - t90, job_s - t99, busy, submit_s


def main():
    scene_file = os.path.join(work, "tail.json")
    with open(scene_file, "w") as f:
        json.dump(scene(args.glass), f)
    url, token = start_collector()
    for i in range(args.workers):
        log = open(os.path.join(work, f"worker{i}.log"), "w")
        procs.append(subprocess.Popen([args.dtraced, "--role", "worker", "--collector", url, "--token-file", token,
                                       "--threads", "1", "--name", f"tail-{i}"],
                                      stdout=subprocess.DEVNULL, stderr=log))
    orders = ["row", "cost"] if args.order == "both" else [args.order]
    load = os.getloadavg()
    print(f"job_tail: {args.width}x{args.height} at {args.samples} spp, glass cluster in the {args.glass} "
          f"rows, {args.workers} workers x 1 thread, medians of {args.runs} runs, "
          f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} at the start")
    print()
    print("| tile px | order | tiles | job s | submit s | last 10 % of tiles s | share of job | last 1 % s | share "
          "| workers busy |")
    print("|--:|:--|--:|--:|--:|--:|--:|--:|--:|--:|")
    targets = []
    for tile in [int(t) for t in args.tiles.split(",")]:
        rows = {o: [] for o in orders}
        for i in range(args.runs):
            for o in orders:  # alternating: both orders see the same load
                rows[o].append(run(url, token, scene_file, tile, i, o))
        job_medians = {}
        for o in orders:
            r_o = rows[o]
            total = r_o[0][0]
            job_s = statistics.median(r[1] for r in r_o)
            t10 = statistics.median(r[2] for r in r_o)
            t1 = statistics.median(r[3] for r in r_o)
            share10 = statistics.median(r[2] / r[1] for r in r_o)
            share1 = statistics.median(r[3] / r[1] for r in r_o)
            busy = statistics.median(r[4] for r in r_o)
            submit_s = statistics.median(r[5] for r in r_o)
            job_medians[o] = job_s
            print(f"| {tile} | {o} | {total} | {job_s:.2f} | {submit_s:.2f} | {t10:.2f} | {share10:.1%} | {t1:.2f} "
                  f"| {share1:.1%} | {busy:.0%} |", flush=True)
            if o == "cost":
                verdict = "MET" if share10 <= 0.10 else "MISSED"
                targets.append(f"{tile} px, cost order: last 10 % of tiles = {share10:.1%} of the job "
                               f"(target <= 10 %): {verdict}")
        if len(orders) == 2:
            targets.append(f"{tile} px: cost order job time / row order job time = "
                           f"{job_medians['cost'] / job_medians['row']:.2f}")
    if targets:
        print()
        for line in targets:
            print(line)
    stop_all()


try:
    main()
except KeyboardInterrupt:
    stop_all()
    sys.exit(130)
