#!/usr/bin/env python3
"""The collector's web page in a real browser (issue 14).

Starts a collector and a worker on 127.0.0.1 (ephemeral port, temporary state directory and
token) and drives headless Chromium through Selenium. It checks, in order:
  - no request without credentials succeeds: every /ui/api route without the session cookie is
    401, a bearer token there is 401 too, a state change with a foreign Origin is 403 (also at
    sign-in), one without the CSRF header is 403, and /v1 with only the cookie is 401;
  - the page at / shows the sign-in form, and signs in with the farm token;
  - two submitted jobs appear in the jobs table;
  - the preview of a job with no worker yet is black; a region typed in the keyboard form, then
    a rectangle dragged on the preview, are sent as focus requests, and once a
    one-tile-at-a-time worker starts, the dragged region's tiles are the first ones stored and
    the typed region's next (their seq order in the tile delta);
  - the worker appears in the workers list as active, the preview changed as tiles landed, and
    with the worker stopped (SIGSTOP) the canvas equals the collector's partial PNG pixel for
    pixel; hovering a stored tile names its worker;
  - cancelling the other job from the page (through the confirmation dialog) cancels it;
  - once the job is done the canvas equals the final PNG pixel for pixel, and nothing on the
    page moved while it polled;
  - at 390 px wide the page does not scroll sideways and the jobs' buttons are on screen;
  - the stopped worker is marked quiet, then leaves the list;
  - a hidden tab sends no request, and polls again once shown;
  - sign-out shows the sign-in form again;
  - a viewer credential (made with POST /v1/credentials) signs in read-only: "read-only
    (viewer)" shows, a queued job's row has no pause or cancel button, the priority cannot be
    set, the region form is gone, and a state change forced past the page gets 403;
  - the browser logged no JavaScript error or warning.
Exits 77 (ctest: skipped) only when chromium, chromedriver or python3-selenium is missing.
Needs DTRACED (the binary) and SCENES (the scenes folder) in the environment.
"""

import base64
import http.client
import http.cookies
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time

SKIP = 77


def reexec_with_system_python():
    """Debian's python3-selenium lives in /usr/bin/python3's path; a python3 earlier on PATH
    (pyenv, a venv) does not see it."""
    system = "/usr/bin/python3"
    if os.path.realpath(sys.executable) != os.path.realpath(system) and os.path.exists(system) \
            and not os.environ.get("DTRACED_BROWSER_REEXEC"):
        os.environ["DTRACED_BROWSER_REEXEC"] = "1"
        os.execv(system, [system] + sys.argv)


try:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.common.exceptions import WebDriverException
except ImportError:
    reexec_with_system_python()
    print("SKIP: python3-selenium is not installed (apt-get install python3-selenium)")
    sys.exit(SKIP)

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
if not CHROMIUM or not CHROMEDRIVER:
    print("SKIP: chromium and chromium-driver are needed (apt-get install chromium chromium-driver)")
    sys.exit(SKIP)

DTRACED = os.environ.get("DTRACED")
SCENES = os.environ.get("SCENES")
if not DTRACED or not SCENES:
    print("FAIL: set DTRACED to the dtraced binary and SCENES to the scenes folder")
    sys.exit(1)

DEADLINE = float(os.environ.get("DEADLINE", "60"))  # the longest any one wait may take
WIDTH, HEIGHT, TILE, SAMPLES = 128, 96, 16, 256

passed = 0


def ok(what):
    global passed
    passed += 1
    print(f"ok: {what}", flush=True)


class Failure(Exception):
    pass


def check(cond, what):
    if not cond:
        raise Failure(what)
    ok(what)


def wait_for(what, fn, deadline=DEADLINE, step=0.05):
    """Polls fn until it answers something true; fails naming `what` after `deadline` s."""
    end = time.monotonic() + deadline
    last = None
    while time.monotonic() < end:
        try:
            last = fn()
        except Failure:
            raise
        except Exception as e:  # a transient error while the page or a process changes
            last = e
        if last and not isinstance(last, Exception):
            return last
        time.sleep(step)
    raise Failure(f"{what}: not within {deadline:.0f} s (last: {last!r})")


class Farm:
    """A collector (and workers) in a temporary directory; everything is killed on close."""

    def __init__(self, extra_collector_flags):
        self.dir = tempfile.mkdtemp(prefix="dtraced-web-")
        self.token = f"web-test-{os.getpid()}-token"
        self.token_file = os.path.join(self.dir, "token")
        with open(self.token_file, "w") as f:
            f.write(self.token + "\n")
        self.procs = []
        self.logs = []
        log = os.path.join(self.dir, "collector.log")
        self.collector = self.spawn(
            [DTRACED, "--role", "collector", "--listen", "127.0.0.1:0", "--state-dir",
             os.path.join(self.dir, "state"), "--token-file", self.token_file] + extra_collector_flags,
            log)
        self.port = wait_for("the collector listens", lambda: self.port_from_log(log), step=0.1)
        self.host = f"127.0.0.1:{self.port}"
        self.url = f"http://{self.host}"

    def spawn(self, argv, log):
        f = open(log, "ab")
        p = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=f)
        f.close()
        self.procs.append(p)
        self.logs.append(log)
        return p

    def port_from_log(self, log):
        if self.collector.poll() is not None:
            raise Failure("the collector exited at start")
        with open(log, errors="replace") as f:
            m = re.findall(r"listening on .* port (\d+)", f.read())
        return int(m[-1]) if m else None

    def worker(self, name, *flags):
        return self.spawn([DTRACED, "--role", "worker", "--collector", self.url, "--token-file",
                           self.token_file, "--name", name, "--grace-seconds", "5", *flags],
                          os.path.join(self.dir, f"{name}.log"))

    def client(self, *args):
        out = subprocess.run([DTRACED, *args, "--collector", self.url, "--token-file", self.token_file],
                             capture_output=True, text=True, timeout=DEADLINE)
        if out.returncode != 0:
            raise Failure(f"dtraced {' '.join(args)} exited {out.returncode}: {out.stderr.strip()}")
        return out.stdout

    def request(self, method, path, body=None, headers=None):
        """One HTTP request; answers (status, headers, body bytes)."""
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=DEADLINE)
        try:
            h = dict(headers or {})
            data = None
            if body is not None:
                data = json.dumps(body).encode()
                h["Content-Type"] = "application/json"
            conn.request(method, path, body=data, headers=h)
            r = conn.getresponse()
            return r.status, r.headers, r.read()
        finally:
            conn.close()

    def bearer(self):
        return {"Authorization": f"Bearer {self.token}"}

    def v1(self, path):
        status, _, body = self.request("GET", path, headers=self.bearer())
        if status != 200:
            raise Failure(f"GET {path}: {status} {body[:200]!r}")
        return body

    def job(self, job_id):
        return json.loads(self.v1(f"/v1/jobs/{job_id}"))

    def close(self):
        for p in self.procs:
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGCONT)
                    p.kill()
                except ProcessLookupError:
                    pass
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass

    def show_logs(self):
        for log in self.logs:
            try:
                with open(log, errors="replace") as f:
                    lines = f.readlines()[-25:]
            except OSError:
                continue
            print(f"--- {log} (last {len(lines)} lines)")
            sys.stdout.write("".join(lines))


class Session:
    """A signed-in page session seen from Python: its cookie and CSRF value."""

    def __init__(self, farm, token=None):
        self.farm = farm
        status, headers, body = farm.request("POST", "/ui/session", {"token": token or farm.token},
                                             {"Origin": farm.url})
        if status != 200:
            raise Failure(f"POST /ui/session with the token: {status} {body[:200]!r}")
        answer = json.loads(body)
        self.csrf = answer["csrf"]
        self.role = answer.get("role")
        jar = http.cookies.SimpleCookie()
        for value in headers.get_all("Set-Cookie") or []:
            jar.load(value)
        if "dtraced_session" not in jar:
            raise Failure("POST /ui/session set no dtraced_session cookie")
        morsel = jar["dtraced_session"]
        self.cookie_flags = (bool(morsel["httponly"]), morsel["samesite"], morsel["path"])
        self.cookie = f"dtraced_session={jar['dtraced_session'].value}"

    def get(self, path):
        return self.farm.request("GET", path, headers={"Cookie": self.cookie})

    def json(self, path):
        status, _, body = self.get(path)
        if status != 200:
            raise Failure(f"GET {path} with the session: {status} {body[:200]!r}")
        return json.loads(body)


def check_access(farm, job_id):
    """No request without credentials succeeds (and none with the wrong kind of them)."""
    reads = ["/ui/api/jobs", f"/ui/api/jobs/{job_id}", "/ui/api/workers",
             f"/ui/api/jobs/{job_id}/image", f"/ui/api/jobs/{job_id}/tiles?since=0"]
    writes = [(f"/ui/api/jobs/{job_id}/{verb}", None) for verb in ("cancel", "pause", "resume", "requeue")]
    writes += [(f"/ui/api/jobs/{job_id}/priority", {"priority": 5}),
               (f"/ui/api/jobs/{job_id}/focus", {"x": 0, "y": 0, "width": 1, "height": 1})]
    same = {"Origin": farm.url}
    for path in reads:
        check(farm.request("GET", path)[0] == 401, f"GET {path} without the cookie is 401")
        check(farm.request("GET", path, headers=farm.bearer())[0] == 401,
              f"GET {path} with the bearer token (not a session) is 401")
    for path, body in writes:
        check(farm.request("POST", path, body, same)[0] == 401, f"POST {path} without the cookie is 401")
    status, _, body = farm.request("GET", "/ui/session")
    check(status == 200 and json.loads(body) == {"signed_in": False},
          "GET /ui/session without the cookie says signed_in false, and nothing else")
    status = farm.request("POST", "/ui/session", {"token": farm.token}, {"Origin": "http://evil.example"})[0]
    check(status == 403, "sign-in with a foreign Origin is 403")
    status = farm.request("POST", "/ui/session", {"token": farm.token},
                          {"Origin": farm.url, "Sec-Fetch-Site": "cross-site"})[0]
    check(status == 403, "sign-in from a cross-site fetch is 403")
    status = farm.request("POST", "/ui/session", {"token": "not-the-token"}, same)[0]
    check(status == 401, "sign-in with a wrong token is 401")

    s = Session(farm)
    check(s.cookie_flags == (True, "Strict", "/ui"),
          f"the session cookie is HttpOnly, SameSite=Strict, Path=/ui ({s.cookie_flags})")
    cookie = {"Cookie": s.cookie}
    check(s.get("/ui/api/jobs")[0] == 200, "GET /ui/api/jobs with the cookie is 200")
    check(farm.request("GET", "/v1/jobs", headers=cookie)[0] == 401, "GET /v1/jobs with only the cookie is 401")
    check(farm.request("POST", f"/v1/jobs/{job_id}/pause", None, cookie)[0] == 401,
          "POST /v1/jobs/ID/pause with only the cookie is 401")
    path = f"/ui/api/jobs/{job_id}/priority"
    status = farm.request("POST", path, {"priority": 1}, {**cookie, "Origin": "http://evil.example",
                                                           "X-Dtraced-CSRF": s.csrf})[0]
    check(status == 403, "a session's POST with a foreign Origin is 403")
    check(farm.request("POST", path, {"priority": 1}, {**cookie, **same})[0] == 403,
          "a session's POST without the CSRF header is 403")
    check(farm.request("POST", path, {"priority": 1}, {**cookie, **same, "X-Dtraced-CSRF": "0" * 64})[0] == 403,
          "a session's POST with a wrong CSRF value is 403")
    check(farm.job(job_id)["priority"] == 0, "none of the refused requests changed the job")
    return s


def make_driver(user_data):
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              f"--user-data-dir={user_data}", "--window-size=1280,1000", "--no-first-run",
              "--disable-extensions", "--disable-background-networking", "--password-store=basic"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    # Chromium's start can fail on a loaded machine ("DevToolsActivePort file doesn't exist"):
    # one more try, then the error.
    for attempt in (1, 2):
        try:
            return webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)
        except WebDriverException as e:
            if attempt == 2:
                raise
            print(f"chromium did not start ({str(e).splitlines()[0]}); trying again", flush=True)
            time.sleep(1)


# Reads the preview canvas (through a copy: Chromium warns about repeated readbacks of one
# canvas), and decodes a PNG given in base64 into a second canvas: answers
# {width, height, same, differing, nonblack_canvas, nonblack_png} (RGB compared, alpha ignored).
COMPARE_JS = """
const [b64, done] = [arguments[0], arguments[arguments.length - 1]];
(async () => {
  const canvas = document.getElementById('preview');
  const w = canvas.width, h = canvas.height;
  const copy = new OffscreenCanvas(w, h).getContext('2d');  // one readback per canvas: no
  copy.drawImage(canvas, 0, 0);                               // willReadFrequently warning
  const a = copy.getImageData(0, 0, w, h).data;
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const bmp = await createImageBitmap(new Blob([bytes], {type: 'image/png'}),
                                      {colorSpaceConversion: 'none', premultiplyAlpha: 'none'});
  if (bmp.width !== w || bmp.height !== h) {
    done({error: `canvas ${w}x${h}, png ${bmp.width}x${bmp.height}`});
    return;
  }
  const other = new OffscreenCanvas(w, h).getContext('2d');
  other.drawImage(bmp, 0, 0);
  const b = other.getImageData(0, 0, w, h).data;
  let differing = 0, nonA = 0, nonB = 0, first = null;
  for (let i = 0; i < a.length; i += 4) {
    const da = a[i] | a[i + 1] | a[i + 2], db = b[i] | b[i + 1] | b[i + 2];
    if (da) ++nonA;
    if (db) ++nonB;
    if (a[i] !== b[i] || a[i + 1] !== b[i + 1] || a[i + 2] !== b[i + 2]) {
      if (first === null) first = [(i / 4) % w, Math.floor(i / 4 / w), [a[i], a[i+1], a[i+2]], [b[i], b[i+1], b[i+2]]];
      ++differing;
    }
  }
  done({width: w, height: h, differing, first, nonblack_canvas: nonA, nonblack_png: nonB});
})().catch((e) => done({error: String(e)}));
"""

NONBLACK_JS = """
const c = document.getElementById('preview');
const copy = new OffscreenCanvas(c.width, c.height).getContext('2d');
copy.drawImage(c, 0, 0);
const d = copy.getImageData(0, 0, c.width, c.height).data;
let n = 0;
for (let i = 0; i < d.length; i += 4) if (d[i] | d[i + 1] | d[i + 2]) ++n;
return n;
"""


def compare_with_png(driver, farm, job_id):
    png = farm.v1(f"/v1/jobs/{job_id}/image?format=png")
    return driver.execute_async_script(COMPARE_JS, base64.b64encode(png).decode())


def css_point(driver, element, x, y):
    """Selenium's offset (from the element's centre) of image pixel (x, y)'s centre."""
    r = driver.execute_script(
        "const b = arguments[0].getBoundingClientRect(); return [b.width, b.height];", element)
    sx, sy = r[0] / WIDTH, r[1] / HEIGHT
    return round((x + 0.5) * sx - r[0] / 2), round((y + 0.5) * sy - r[1] / 2)


def row(driver, job_id):
    rows = driver.find_elements(By.CSS_SELECTOR, f'#jobs tbody tr[data-job="{job_id}"]')
    return rows[0] if rows else None


def worker_row(driver, name):
    rows = driver.find_elements(By.CSS_SELECTOR, f'#workers tbody tr[data-worker="{name}"]')
    return rows[0] if rows else None


def text_of(driver, element_id):
    return driver.find_element(By.ID, element_id).text


def console_problems(driver):
    """The browser's console errors and warnings (Chromium logs every failed request as an error)."""
    bad = []
    for entry in driver.get_log("browser"):
        if entry.get("level") not in ("SEVERE", "WARNING"):
            continue
        bad.append(f"{entry.get('level')}: {entry.get('message', '')}")
    return bad


def run(farm, driver):
    scene = os.path.join(SCENES, "diffuse.json")
    common = ["--width", str(WIDTH), "--height", str(HEIGHT), "--tile-size", str(TILE), "-s", str(SAMPLES)]
    job_a = int(farm.client("submit", scene, "-o", "web-a.png", *common).strip())
    job_b = int(farm.client("submit", scene, "-o", "web-b.png", "--priority", "-10", *common).strip())
    session = check_access(farm, job_a)

    # Sign in.
    console_at_load = []
    driver.get(farm.url + "/")
    driver.execute_script("performance.setResourceTimingBufferSize(100000)")  # (250 by default)
    wait_for("the sign-in form shows", lambda: driver.find_element(By.ID, "signin-view").is_displayed())
    console_at_load = console_problems(driver)
    token = driver.find_element(By.ID, "token")
    check(token.get_attribute("type") == "password", "the token field is a password field")
    label = driver.find_element(By.CSS_SELECTOR, 'label[for="token"]')
    check(label.text != "", "the token field has a label")
    token.send_keys(farm.token + Keys.RETURN)
    wait_for("the page signs in", lambda: driver.find_element(By.ID, "app-view").is_displayed())
    ok("signed in with the farm token")
    check(driver.execute_script("return window.localStorage.length + window.sessionStorage.length") == 0,
          "nothing is kept in the browser's storage")
    check("dtraced_session" not in driver.execute_script("return document.cookie"),
          "document.cookie does not hold the session cookie")

    # Both jobs appear.
    wait_for("job A's row appears", lambda: row(driver, job_a))
    wait_for("job B's row appears", lambda: row(driver, job_b))
    ok("the submitted jobs appear in the jobs table")
    check("queued" in row(driver, job_a).text, "job A shows as queued")

    # The preview of job A: black, nothing rendered yet.
    row(driver, job_a).find_element(By.CSS_SELECTOR, f'button[aria-label="Preview job {job_a}"]').click()
    canvas = driver.find_element(By.ID, "preview")
    wait_for("the preview takes the image's size",
             lambda: canvas.get_attribute("width") == str(WIDTH) and canvas.get_attribute("height") == str(HEIGHT)
             and canvas.get_attribute("data-ready") == "true")
    check(driver.execute_script(NONBLACK_JS) == 0, "the preview of a job with no tile stored is black")

    # The keyboard way first: the form's pixel (120, 90), in the last tile, goes to the front...
    for field, value in (("focus-x", 120), ("focus-y", 90), ("focus-w", 1), ("focus-h", 1)):
        box = driver.find_element(By.ID, field)
        box.clear()
        box.send_keys(str(value))
    driver.find_element(By.ID, "focus-h").send_keys(Keys.RETURN)
    wait_for("the page reports the keyboard focus request",
             lambda: re.search(r"^1 tiles .* at \(120, 90\) moved to the front", text_of(driver, "focus-result")))
    ok("the keyboard form sends a region (1 tile moved)")

    # ...then a rectangle dragged over the 2x2 tiles at tile (2, 2)..(3, 3) goes before it.
    overlay = driver.find_element(By.ID, "overlay")
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", overlay)
    x0, y0, x1, y1 = 2 * TILE + 3, 2 * TILE + 3, 4 * TILE - 4, 4 * TILE - 4
    ox0, oy0 = css_point(driver, overlay, x0, y0)
    ox1, oy1 = css_point(driver, overlay, x1, y1)
    ActionChains(driver).move_to_element_with_offset(overlay, ox0, oy0).click_and_hold() \
        .move_by_offset((ox1 - ox0) // 2, (oy1 - oy0) // 2).move_by_offset(ox1 - ox0 - (ox1 - ox0) // 2,
                                                                           oy1 - oy0 - (oy1 - oy0) // 2) \
        .release().perform()
    result = wait_for("the page reports the focus request",
                      lambda: re.search(r"^(\d+) tiles .* at \((?!120, 90\)).* moved to the front",
                                        text_of(driver, "focus-result")))
    moved = int(result.group(1))
    fx, fy, fw, fh = (int(driver.find_element(By.ID, i).get_attribute("value"))
                      for i in ("focus-x", "focus-y", "focus-w", "focus-h"))
    check(abs(fx - x0) <= 1 and abs(fy - y0) <= 1 and abs(fx + fw - 1 - x1) <= 1 and abs(fy + fh - 1 - y1) <= 1,
          f"the dragged rectangle maps to image pixels ({fx}, {fy}, {fw}x{fh} for ({x0}, {y0})-({x1}, {y1}))")
    check(moved == 4, f"the collector moved the region's 4 tiles forward (it says {moved})")

    # One worker, one tile at a time: the region's tiles are stored first.
    worker = farm.worker("web-w1", "-t", "1", "--max-unacknowledged", "1")
    wait_for("the worker stores the regions' tiles", lambda: farm.job(job_a)["tiles_done"] >= moved + 1, step=0.01)
    worker.send_signal(signal.SIGSTOP)
    done_at_stop = farm.job(job_a)["tiles_done"]
    total = farm.job(job_a)["tiles_total"]
    check(done_at_stop < total, f"the worker was stopped mid-job ({done_at_stop} of {total} tiles)")
    delta = session.json(f"/ui/api/jobs/{job_a}/tiles?since=0")
    by_seq = sorted(delta["tiles"], key=lambda t: t["seq"])
    first = by_seq[:moved]

    def in_region(t):
        return t["x"] < fx + fw and fx < t["x"] + t["width"] and t["y"] < fy + fh and fy < t["y"] + t["height"]

    check(len(first) == moved and all(in_region(t) for t in first),
          f"the first {moved} tiles stored are the region's: {[(t['x'], t['y'], t['seq']) for t in first]}")
    nxt = by_seq[moved]
    check(nxt["x"] <= 120 < nxt["x"] + nxt["width"] and nxt["y"] <= 90 < nxt["y"] + nxt["height"],
          f"the next tile stored is the keyboard region's (it is at ({nxt['x']}, {nxt['y']}))")
    check(all(t["worker"] == "web-w1" for t in delta["tiles"]), "each stored tile names its worker")

    # The worker shows as active; the preview caught up with what is stored.
    wait_for("the worker appears in the workers list",
             lambda: worker_row(driver, "web-w1") and "active" in worker_row(driver, "web-w1").text)
    ok("the worker appears in the workers list, marked active")

    def caught_up():
        d = session.json(f"/ui/api/jobs/{job_a}/tiles?since=0")
        return canvas.get_attribute("data-seq") == str(d["seq"]) and canvas.get_attribute("data-ready") == "true"

    wait_for("the preview draws every stored tile", caught_up)
    cmp = compare_with_png(driver, farm, job_a)
    check("error" not in cmp, f"the partial PNG decodes at the canvas's size ({cmp})")
    check(0 < cmp["nonblack_canvas"] < WIDTH * HEIGHT,
          f"the preview changed as tiles landed ({cmp['nonblack_canvas']} of {WIDTH * HEIGHT} pixels drawn)")
    check(cmp["differing"] == 0,
          f"mid-job the preview equals the partial PNG pixel for pixel ({cmp['differing']} differ, first {cmp['first']})")

    # Hover over a stored tile: its worker.
    t = first[0]
    hx, hy = css_point(driver, overlay, t["x"] + t["width"] // 2, t["y"] + t["height"] // 2)
    ActionChains(driver).move_to_element_with_offset(overlay, hx, hy).perform()
    wait_for("hovering a stored tile names its worker", lambda: "web-w1" in text_of(driver, "tip"))
    ok("hovering a stored tile names its worker")

    # Cancel job B from the page, through the confirmation dialog.
    row(driver, job_b).find_element(By.CSS_SELECTOR, f'button[aria-label="Cancel job {job_b}"]').click()
    dialog = driver.find_element(By.ID, "confirm")
    wait_for("the confirmation dialog opens", lambda: dialog.is_displayed())
    driver.find_element(By.ID, "confirm-yes").click()
    wait_for("job B is cancelled", lambda: farm.job(job_b)["state"] == "cancelled")
    ok("cancel from the page (confirmed in its dialog) cancels the job")
    wait_for("job B's row shows it", lambda: "cancelled" in row(driver, job_b).text)
    ok("the jobs table shows the cancellation")

    # Let the worker finish job A: the canvas ends equal to the final PNG. Meanwhile the page's
    # layout stays put: its sections and the jobs' rows neither move nor change height.
    layout_js = """return [...['preview-title', 'focus-form', 'workers-title'].map((id) =>
        document.getElementById(id).getBoundingClientRect().top + window.scrollY),
      ...[...document.querySelectorAll('#jobs tbody tr')].map((tr) => tr.getBoundingClientRect().height)]
      .map((v) => Math.round(v * 10) / 10);"""
    layouts = [driver.execute_script(layout_js)]
    worker.send_signal(signal.SIGCONT)
    while farm.job(job_a)["state"] != "done":
        layouts.append(driver.execute_script(layout_js))
        time.sleep(0.1)
    time.sleep(1.2)  # the page's next poll shows the job done
    layouts.append(driver.execute_script(layout_js))
    check(len(layouts) >= 3 and all(l == layouts[0] for l in layouts),
          f"nothing moved while the page polled ({len(layouts)} samples; {sorted(set(map(tuple, layouts)))})")
    wait_for("the preview shows the finished image",
             lambda: canvas.get_attribute("data-written") == "true" or
             canvas.get_attribute("data-seq") == str(session.json(f"/ui/api/jobs/{job_a}/tiles?since=0")["seq"]) and
             canvas.get_attribute("data-state") == "done")
    cmp = compare_with_png(driver, farm, job_a)
    check("error" not in cmp and cmp["differing"] == 0,
          f"once done the preview equals the PNG pixel for pixel ({cmp})")
    wait_for("job A's row shows done", lambda: "done" in row(driver, job_a).text)
    ok("the jobs table shows the job done")

    # Stop the worker: quiet, then gone.
    worker.terminate()
    worker.wait(timeout=DEADLINE)
    wait_for("the stopped worker is marked quiet",
             lambda: worker_row(driver, "web-w1") is None or "quiet" in worker_row(driver, "web-w1").text, step=0.1)
    check(worker_row(driver, "web-w1") is not None, "the stopped worker was marked quiet before it left")
    wait_for("the stopped worker leaves the list", lambda: worker_row(driver, "web-w1") is None, step=0.2)
    ok("the stopped worker leaves the workers list")

    # At a phone's width the page does not scroll sideways (a table may, inside its box), and
    # every job's actions stay inside the screen.
    driver.set_window_size(390, 844)
    width = wait_for("the page at 390 px", lambda: driver.execute_script(
        "return innerWidth <= 420 ? document.documentElement.clientWidth : 0"))
    check(driver.execute_script("return document.documentElement.scrollWidth") <= width,
          f"at {width} px the page does not scroll sideways")
    right = driver.execute_script(
        "return Math.max(...[...document.querySelectorAll('#jobs td.actions button')]"
        ".filter((b) => b.offsetParent !== null).map((b) => b.getBoundingClientRect().right))")
    check(right <= width, f"at {width} px the jobs' buttons are on screen (rightmost at {right:.0f})")
    driver.set_window_size(1280, 1000)

    # A hidden tab does not poll, and polls again once shown.
    page = driver.current_window_handle
    driver.execute_script("""window.__vis = [];
        document.addEventListener('visibilitychange',
          () => window.__vis.push([document.visibilityState, performance.now()]));""")
    driver.switch_to.new_window("tab")
    driver.get("about:blank")
    time.sleep(3)  # three polling periods
    driver.close()
    driver.switch_to.window(page)
    vis = wait_for("the page is shown again",
                   lambda: (lambda v: v if len(v) >= 2 and v[-1][0] == "visible" else None)(
                       driver.execute_script("return window.__vis")))
    hidden_at = next(t for state, t in vis if state == "hidden")
    shown_at = vis[-1][1]
    check(shown_at - hidden_at > 2000, f"the page's tab was hidden for {shown_at - hidden_at:.0f} ms")
    during = driver.execute_script(
        "return performance.getEntriesByType('resource').filter((e) => e.startTime > arguments[0] &&"
        " e.startTime < arguments[1]).map((e) => e.name)", hidden_at, shown_at)
    check(during == [], f"no request while the tab was hidden ({during})")
    wait_for("polling resumes once shown", lambda: driver.execute_script(
        "return performance.getEntriesByType('resource').filter((e) => e.startTime >= arguments[0] &&"
        " e.name.includes('/ui/api/jobs')).length", shown_at) > 0)
    ok("polling resumes once the tab is shown")

    # Sign out.
    driver.find_element(By.ID, "signout").click()
    wait_for("sign-out shows the sign-in form", lambda: driver.find_element(By.ID, "signin-view").is_displayed())
    ok("sign-out shows the sign-in form")

    check_viewer(farm, driver, scene, common)

    problems = console_at_load + console_problems(driver)
    check(not problems, "no JavaScript console errors or warnings" + ("" if not problems else f": {problems}"))


def check_viewer(farm, driver, scene, common):
    """A viewer's session watches: no control that changes the farm, and a forced change is 403."""
    job_c = int(farm.client("submit", scene, "-o", "web-c.png", *common).strip())
    status, _, body = farm.request("POST", "/v1/credentials", {"name": "web-viewer", "role": "viewer"},
                                   farm.bearer())
    if status != 201:
        raise Failure(f"POST /v1/credentials for a viewer: {status} {body[:200]!r}")
    ok("POST /v1/credentials makes a viewer credential")
    viewer_token = json.loads(body)["token"]

    token = driver.find_element(By.ID, "token")
    token.clear()
    token.send_keys(viewer_token + Keys.RETURN)
    wait_for("the page signs in as the viewer", lambda: driver.find_element(By.ID, "app-view").is_displayed())
    check(driver.find_element(By.ID, "role-note").is_displayed()
          and text_of(driver, "role-note") == "read-only (viewer)",
          "a viewer's page says read-only (viewer)")
    r = wait_for("job C's row appears", lambda: row(driver, job_c))
    wait_for("job C's row shows it queued", lambda: "queued" in row(driver, job_c).text)
    r = row(driver, job_c)
    shown = [b.text for b in r.find_elements(By.CSS_SELECTOR, "button") if b.is_displayed()]
    check(shown == ["Preview"], f"a viewer sees no pause, cancel or priority button on a queued job ({shown})")
    check(not r.find_element(By.CSS_SELECTOR, "input").is_enabled(), "a viewer cannot edit a job's priority")
    r.find_element(By.CSS_SELECTOR, f'button[aria-label="Preview job {job_c}"]').click()
    wait_for("the viewer's preview shows", lambda: driver.find_element(By.ID, "preview-box").is_displayed())
    check(not driver.find_element(By.ID, "focus-form").is_displayed(), "a viewer's preview has no region form")

    v = Session(farm, viewer_token)
    check(v.role == "viewer", f"the viewer's sign-in answers role viewer ({v.role})")
    check(v.json("/ui/session").get("role") == "viewer", "GET /ui/session says role viewer")
    forced = {"Cookie": v.cookie, "Origin": farm.url, "X-Dtraced-CSRF": v.csrf}
    check(farm.request("POST", f"/ui/api/jobs/{job_c}/cancel", None, forced)[0] == 403,
          "a viewer's forced cancel is 403")
    check(farm.request("POST", f"/ui/api/jobs/{job_c}/focus", {"x": 0, "y": 0, "width": 1, "height": 1},
                       forced)[0] == 403, "a viewer's forced focus is 403")
    check(farm.job(job_c)["state"] == "queued", "the viewer's refused requests changed nothing")

    driver.find_element(By.ID, "signout").click()
    wait_for("the viewer signs out", lambda: driver.find_element(By.ID, "signin-view").is_displayed())
    check(not driver.find_element(By.ID, "role-note").is_displayed(), "signed out, the read-only note is gone")


def main():
    started = time.monotonic()
    farm = Farm(["--worker-quiet-after-s", "1", "--worker-forget-after-s", "5"])
    driver = None
    user_data = tempfile.mkdtemp(prefix="dtraced-chromium-")
    try:
        driver = make_driver(user_data)
        run(farm, driver)
    except Failure as e:
        print(f"FAIL: {e}")
        farm.show_logs()
        return 1
    except Exception as e:  # Selenium or a process: still a failure, with the logs
        print(f"FAIL: {type(e).__name__}: {e}")
        farm.show_logs()
        return 1
    finally:
        if driver is not None:
            driver.quit()
        farm.close()
        shutil.rmtree(user_data, ignore_errors=True)
        shutil.rmtree(farm.dir, ignore_errors=True)
    print(f"{passed} passed in {time.monotonic() - started:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
