#!/usr/bin/env python3
"""Figures of the collector's web page (issue 14), printed as a table:

  - first-load bytes: the document, its three assets and the first API answers (session, jobs,
    workers, and the first tile delta of the selected job), from the Resource Timing API's
    transferSize (headers and body as sent on the wire);
  - bytes per poll for a 1920x1080 job in progress (each resource's mean over ~10 s of polling:
    200s with new tiles, 304s without);
  - the collector's extra CPU (utime + stime from /proc/PID/stat over a fixed interval) with
    5 pages open and polling, against none, while the same job renders;
  - the time from a click on the preview to the first stored tile of the clicked region, with
    2 workers (median of several clicks, each on a region not rendered yet).

Usage: tests/bench/web_page_bench.py [--dtraced build/src/cli/dtraced] [--samples 256]
       [--interval 10] [--clicks 5] [--screenshot docs/images/web-page.png]
Needs chromium, chromium-driver and python3-selenium (Debian: apt-get install chromium
chromium-driver python3-selenium). Uses the helpers of tests/browser/web_page_test.py.
"""

import argparse
import os
import signal
import statistics
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))

parser = argparse.ArgumentParser(description="figures of the collector's web page")
parser.add_argument("--dtraced", default=os.path.join(ROOT, "build", "src", "cli", "dtraced"))
parser.add_argument("--samples", type=int, default=256, help="samples per pixel of the 1920x1080 job")
parser.add_argument("--interval", type=float, default=10.0, help="seconds of each CPU and polling measurement")
parser.add_argument("--clicks", type=int, default=5)
parser.add_argument("--screenshot", help="also write a 1280-px-wide screenshot of a job in progress here")
args = parser.parse_args()
os.environ["DTRACED"] = os.path.abspath(args.dtraced)
os.environ["SCENES"] = os.path.join(ROOT, "scenes")
sys.path.insert(0, os.path.join(ROOT, "tests", "browser"))

import web_page_test as w  # noqa: E402  (after the environment it reads)
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402

W, H, TILE = 1920, 1080, 32
TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid):
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS  # utime, stime (fields 14 and 15)


def cpu_over(pid, seconds):
    a = cpu_seconds(pid)
    time.sleep(seconds)
    return cpu_seconds(pid) - a


def sign_in(driver, farm):
    """Opens the page, and signs in unless the browser's session cookie is still live."""
    driver.get(farm.url + "/")
    driver.execute_script("performance.setResourceTimingBufferSize(100000)")
    w.wait_for("the sign-in form or the page",
               lambda: driver.find_element(By.ID, "signin-view").is_displayed() or
               driver.find_element(By.ID, "app-view").is_displayed())
    if driver.find_element(By.ID, "signin-view").is_displayed():
        driver.find_element(By.ID, "token").send_keys(farm.token + Keys.RETURN)
    w.wait_for("signed in", lambda: driver.find_element(By.ID, "app-view").is_displayed())


def open_preview(driver, job):
    w.wait_for("the job's row", lambda: w.row(driver, job))
    w.row(driver, job).find_element(By.CSS_SELECTOR, f'button[aria-label="Preview job {job}"]').click()
    canvas = driver.find_element(By.ID, "preview")
    w.wait_for("the preview's first delta",
               lambda: canvas.get_attribute("width") == str(W) and canvas.get_attribute("data-ready") == "true")


ENTRIES_JS = """
const nav = performance.getEntriesByType('navigation').map((e) => ({name: e.name, size: e.transferSize, t: 0}));
const res = performance.getEntriesByType('resource').map((e) => ({name: e.name, size: e.transferSize, t: e.startTime}));
return nav.concat(res);
"""


def kind(url):
    path = url.split("://", 1)[-1].split("/", 1)[-1]
    path = "/" + path.split("?", 1)[0]
    if path == "/":
        return "document"
    if path.startswith("/ui/api/jobs/") and path.endswith("/tiles"):
        return "tile delta"
    if path.startswith("/ui/api/jobs/") and path.endswith("/image"):
        return "image"
    return path


def first_load(driver, farm, job):
    sign_in(driver, farm)
    open_preview(driver, job)
    time.sleep(0.3)
    entries = driver.execute_script(ENTRIES_JS)
    firsts = {}
    for e in entries:  # the first of each kind
        firsts.setdefault(kind(e["name"]), e["size"])
    return firsts, len(entries)


def per_poll(driver, seconds):
    start = driver.execute_script("return performance.now()")
    time.sleep(seconds)
    entries = [e for e in driver.execute_script(ENTRIES_JS) if e["t"] >= start]
    by = {}
    for e in entries:
        by.setdefault(kind(e["name"]), []).append(e["size"])
    return by


def main():
    farm = w.Farm(["--worker-quiet-after-s", "5", "--worker-forget-after-s", "60"])
    drivers = []
    rows = []
    try:
        scene = os.path.join(w.SCENES, "diffuse.json")
        job = int(farm.client("submit", scene, "-o", "bench-1080.png", "--width", str(W), "--height", str(H),
                              "--tile-size", str(TILE), "-s", str(args.samples)).strip())
        workers = [farm.worker(f"bench-w{i}", "-t", "1") for i in (1, 2)]
        w.wait_for("tiles land", lambda: farm.job(job)["tiles_done"] >= 20, step=0.1)
        session = w.Session(farm)

        # The collector's CPU with no page open, then with 5.
        idle = cpu_over(farm.collector.pid, args.interval)
        driver = w.make_driver(tempfile.mkdtemp(prefix="dtraced-bench-"))
        drivers.append(driver)
        loaded, n_entries = first_load(driver, farm, job)
        polls = per_poll(driver, args.interval)
        for _ in range(4):
            driver.switch_to.new_window("window")
            sign_in(driver, farm)
            open_preview(driver, job)
        states = []
        for handle in driver.window_handles:
            driver.switch_to.window(handle)
            states.append(driver.execute_script("return document.visibilityState"))
        busy = cpu_over(farm.collector.pid, args.interval)
        idle2 = None
        for handle in driver.window_handles[1:]:
            driver.switch_to.window(handle)
            driver.close()
        driver.switch_to.window(driver.window_handles[0])
        driver.get("about:blank")
        idle2 = cpu_over(farm.collector.pid, args.interval)

        # Click to first stored tile of the region, with the 2 workers.
        open_page = driver
        sign_in(open_page, farm)
        open_preview(open_page, job)
        overlay = open_page.find_element(By.ID, "overlay")
        open_page.execute_script("arguments[0].scrollIntoView({block: 'center'})", overlay)
        times = []
        d = session.json(f"/ui/api/jobs/{job}/tiles?since=0")
        seq = d["seq"]
        stored = {t["tile"] for t in d["tiles"]}
        cols, rows_n = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
        targets = []
        for i in range(args.clicks):  # bottom rows, spread across: far from the render front
            tx, ty = (cols - 1) - i * (cols // (args.clicks + 1)), rows_n - 1 - (i % 3)
            if ty * cols + tx not in stored:
                targets.append((tx, ty))
        for tx, ty in targets:
            px, py = tx * TILE + TILE // 2, ty * TILE + TILE // 2
            b = open_page.execute_script(
                "const b = arguments[0].getBoundingClientRect(); return [b.width, b.height];", overlay)
            ox, oy = round((px + 0.5) * b[0] / W - b[0] / 2), round((py + 0.5) * b[1] / H - b[1] / 2)
            t0 = time.monotonic()
            ActionChains(open_page).move_to_element_with_offset(overlay, ox, oy).click().perform()
            found = None
            while time.monotonic() - t0 < 60 and found is None:
                d = session.json(f"/ui/api/jobs/{job}/tiles?since={seq}")
                for t in d["tiles"]:
                    if t["x"] <= px < t["x"] + t["width"] and t["y"] <= py < t["y"] + t["height"]:
                        found = time.monotonic() - t0
                if not d.get("more"):
                    seq = d["seq"]
                time.sleep(0.01)
            if found is not None:
                times.append(found)
        progress = farm.job(job)
        for p in workers:
            p.send_signal(signal.SIGSTOP)
        time.sleep(1.5)  # the tiles in flight stay out; nothing changes from here on
        still = per_poll(open_page, args.interval)

        doc = loaded.get("document", 0)
        assets = sum(loaded.get(k, 0) for k in ("/ui/app.js", "/ui/app.css", "/ui/favicon.svg"))
        api_first = sum(v for k, v in loaded.items() if k not in ("document", "/ui/app.js", "/ui/app.css",
                                                                   "/ui/favicon.svg"))
        rows.append(("first load: document", f"{doc} B"))
        rows.append(("first load: app.js + app.css + favicon.svg", f"{assets} B"))
        rows.append(("first load: API (session, jobs, workers, first tile delta)", f"{api_first} B"))
        rows.append(("first load: total", f"{doc + assets + api_first} B"))
        for k in sorted(polls):
            sizes = polls[k]
            rows.append((f"per poll: {k} ({len(sizes)} in {args.interval:.0f} s)",
                         f"mean {statistics.mean(sizes):.0f} B, max {max(sizes)} B"))
        for k in sorted(still):
            sizes = still[k]
            rows.append((f"per poll, workers stopped: {k} ({len(sizes)} in {args.interval:.0f} s)",
                         f"mean {statistics.mean(sizes):.0f} B, max {max(sizes)} B"))
        rows.append(("collector CPU, no page", f"{100 * idle / args.interval:.1f} % of a core"))
        rows.append(("collector CPU, 5 pages polling", f"{100 * busy / args.interval:.1f} % of a core"
                     f" (pages: {','.join(states)})"))
        rows.append(("collector CPU, no page again", f"{100 * idle2 / args.interval:.1f} % of a core"))
        rows.append(("extra CPU of 5 pages", f"{100 * (busy - (idle + idle2) / 2) / args.interval:.1f} % of a core"))
        if times:
            rows.append((f"click to the region's first stored tile, 2 workers ({len(times)} clicks)",
                         f"median {1000 * statistics.median(times):.0f} ms "
                         f"(min {1000 * min(times):.0f}, max {1000 * max(times):.0f})"))
        rows.append(("job at the end", f"{progress['state']}, {progress['tiles_done']}/{progress['tiles_total']} tiles,"
                     f" {args.samples} spp"))

        if args.screenshot:
            screenshot(farm, args.screenshot)
    finally:
        for d in drivers:
            d.quit()
        farm.close()
    width = max(len(r[0]) for r in rows)
    print(f"{'figure':<{width}}  value")
    for name, value in rows:
        print(f"{name:<{width}}  {value}")


def screenshot(farm, path):
    """A 1280-px-wide page with a job in progress: some tiles stored, some being rendered."""
    scene = os.path.join(w.SCENES, "showcase.json")
    job = int(farm.client("submit", scene, "-o", "shot.png", "--width", "960", "--height", "540",
                          "--tile-size", "48", "-s", "64", "--priority", "10").strip())
    farm.client("submit", scene, "-o", "shot-next.png", "--width", "640", "--height", "360", "-s", "64")
    workers = [farm.worker(f"render-{i}", "-t", "1") for i in (3, 4)]
    total = farm.job(job)["tiles_total"]
    driver = w.make_driver(tempfile.mkdtemp(prefix="dtraced-shot-"))
    try:
        sign_in(driver, farm)
        w.wait_for("the job's row", lambda: w.row(driver, job))
        w.row(driver, job).find_element(By.CSS_SELECTOR, f'button[aria-label="Preview job {job}"]').click()
        canvas = driver.find_element(By.ID, "preview")
        w.wait_for("the preview", lambda: canvas.get_attribute("width") == "960")
        h = driver.execute_script("return document.documentElement.scrollHeight")
        driver.set_window_size(1280, h + 140)
        w.wait_for("the showcase is half done", lambda: farm.job(job)["tiles_done"] >= total * 0.45, step=0.05)
        time.sleep(1.2)  # one more poll of every table
        driver.save_screenshot(path)
    finally:
        driver.quit()
        for p in workers:
            p.kill()
    print(f"screenshot: {path}")


if __name__ == "__main__":
    main()
