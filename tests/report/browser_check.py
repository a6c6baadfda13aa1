#!/usr/bin/env python3
"""Opens HTML reports (or PNG figures) in headless Chromium and checks that they render.

Talks to Chromium over the DevTools protocol on a pipe (--remote-debugging-pipe: commands on the
browser's fd 3, replies on fd 4, NUL-terminated JSON), so nothing beyond Python's standard
library and Debian's `chromium` is needed. A page fails when
  - a script throws (Runtime.exceptionThrown) or logs an error (console.error, Log errors such as
    a resource that failed to load), or
  - an <img> did not load or decode (not complete, or naturalWidth 0), or the page has none
    where --min-images asks for some, or
  - a link to a local file (e.g. index.html -> compare/report.html) points to no file, or
  - the page is wider than the window (1280 px): a table, an image or a line that overflows.
Each page gets a full-page screenshot (PNG) in --screenshots.

Usage: browser_check.py [--screenshots DIR] [--min-images N] PAGE...
       browser_check.py --self-test DIR   (a broken page must be caught; exit 0 if it is)
Exit codes: 0 all pages fine, 1 a page failed, 77 chromium not found (ctest: skipped).
"""
import argparse
import base64
import fcntl
import json
import os
import pathlib
import select
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.parse

SKIP = 77


def find_chromium():
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """One headless Chromium driven over --remote-debugging-pipe."""

    def __init__(self, exe, profile_dir, timeout_s=30):
        self.timeout_s = timeout_s
        to_browser_r, to_browser_w = os.pipe()
        from_browser_r, from_browser_w = os.pipe()
        # Move the child's ends above 3 and 4 first so the dup2 below cannot clobber them.
        child_in = fcntl.fcntl(to_browser_r, fcntl.F_DUPFD, 100)
        child_out = fcntl.fcntl(from_browser_w, fcntl.F_DUPFD, 100)
        os.close(to_browser_r)
        os.close(from_browser_w)

        def child_fds():
            os.dup2(child_in, 3)
            os.dup2(child_out, 4)

        args = [exe, "--headless=new", "--remote-debugging-pipe", "--no-sandbox",
                "--disable-gpu", "--no-first-run", "--no-default-browser-check",
                "--disable-extensions", "--hide-scrollbars", "--mute-audio",
                "--allow-file-access-from-files", f"--user-data-dir={profile_dir}", "about:blank"]
        # Chromium's own log goes to a file: an unread pipe could fill and stall the browser.
        self.log_path = os.path.join(profile_dir, "chromium.log")
        self.log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(args, pass_fds=(3, 4), preexec_fn=child_fds,
                                     stdout=self.log, stderr=self.log)
        os.close(child_in)
        os.close(child_out)
        self.wfd, self.rfd = to_browser_w, from_browser_r
        self.buf = b""
        self.next_id = 0
        self.events = []

    def _read_message(self, deadline):
        while b"\0" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no reply from chromium")
            ready, _, _ = select.select([self.rfd], [], [], left)
            if ready:
                chunk = os.read(self.rfd, 1 << 20)
                if not chunk:
                    with open(self.log_path, "rb") as f:
                        err = f.read().decode(errors="replace")
                    raise RuntimeError("chromium closed the DevTools pipe\n" + err[-2000:])
                self.buf += chunk
        msg, self.buf = self.buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method, params=None, session=None):
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self.wfd, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + self.timeout_s
        while True:
            m = self._read_message(deadline)
            if m.get("id") == self.next_id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})
            self.events.append(m)

    def wait_event(self, method, session, timeout_s):
        deadline = time.monotonic() + timeout_s
        while True:
            for i, e in enumerate(self.events):
                if e.get("method") == method and e.get("sessionId") == session:
                    return self.events.pop(i)
            self.events.append(self._read_message(deadline))

    def close(self):
        try:
            self.call("Browser.close")
        except Exception:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self.wfd)
        os.close(self.rfd)
        self.log.close()


IMAGE_CHECK = """(async () => {
  const imgs = Array.from(document.images);
  await Promise.all(imgs.map(i => i.decode().catch(() => null)));
  return JSON.stringify({
    count: imgs.length,
    broken: imgs.filter(i => !i.complete || i.naturalWidth === 0)
                .map(i => (i.alt || '') + ' ' + (i.src || '').slice(0, 60)),
    sizes: imgs.map(i => [i.naturalWidth, i.naturalHeight]),
    links: Array.from(document.links).map(a => a.href).filter(h => h.startsWith('file:')),
    title: document.title,
    scroll_width: document.documentElement.scrollWidth,
    window_width: window.innerWidth,
  });
})()"""


def check_page(browser, path, shot_path, min_images, width=1280):
    """Returns a list of problems (empty when the page is fine) and the image count."""
    target = browser.call("Target.createTarget", {"url": "about:blank"})["targetId"]
    session = browser.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
    for domain in ("Page", "Runtime", "Log"):
        browser.call(f"{domain}.enable", session=session)
    browser.call("Emulation.setDeviceMetricsOverride",
                 {"width": width, "height": 900, "deviceScaleFactor": 1, "mobile": False}, session)
    url = pathlib.Path(path).resolve().as_uri()
    nav = browser.call("Page.navigate", {"url": url}, session)
    problems = []
    if nav.get("errorText"):
        problems.append(f"navigation failed: {nav['errorText']}")
    browser.wait_event("Page.loadEventFired", session, 30)
    res = browser.call("Runtime.evaluate", {"expression": IMAGE_CHECK, "awaitPromise": True,
                                            "returnByValue": True}, session)
    info = json.loads(res["result"]["value"])
    for b in info["broken"]:
        problems.append(f"image did not load or decode: {b}")
    for link in info["links"]:
        target_path = urllib.parse.unquote(urllib.parse.urlparse(link).path)
        if not os.path.exists(target_path):
            problems.append(f"link to a missing file: {link}")
    # A table or figure wider than the window widens the whole page (tables scroll inside
    # their own box instead).
    if info["scroll_width"] > info["window_width"] + 1:
        problems.append(f"page {info['scroll_width']} px wide in a {info['window_width']} px "
                        "window: something overflows (a table, an image, a line of text)")
    if info["count"] < min_images:
        problems.append(f"{info['count']} images, expected at least {min_images}")
    # Full-page screenshot: size the viewport to the content.
    metrics = browser.call("Page.getLayoutMetrics", session=session)
    content = metrics.get("cssContentSize") or metrics["contentSize"]
    height = int(min(max(content["height"], 300), 16000))
    browser.call("Emulation.setDeviceMetricsOverride",
                 {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False}, session)
    shot = browser.call("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True}, session)
    pathlib.Path(shot_path).write_bytes(base64.b64decode(shot["data"]))
    # Errors reported while loading (events collected during the calls above).
    for e in [e for e in browser.events if e.get("sessionId") == session]:
        m, p = e.get("method"), e.get("params", {})
        if m == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            problems.append("script error: " + (d.get("exception", {}).get("description") or d.get("text", "")))
        elif m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            problems.append("console." + p["type"] + ": " + " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
        elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            en = p["entry"]
            problems.append(f"log error: {en.get('text', '')} {en.get('url', '')}".strip())
    browser.events = [e for e in browser.events if e.get("sessionId") != session]
    browser.call("Target.closeTarget", {"targetId": target})
    return problems, info


def run(pages, shots_dir, min_images):
    exe = find_chromium()
    if not exe:
        print("SKIPPED: chromium not found (Debian: apt-get install chromium; scripts/setup.sh "
              "installs it)")
        return SKIP
    os.makedirs(shots_dir, exist_ok=True)
    failed = 0
    with tempfile.TemporaryDirectory() as profile:
        browser = Browser(exe, profile)
        try:
            for page in pages:
                name = pathlib.Path(page).resolve()
                stem = "_".join(name.parts[-3:]).replace(".", "_")
                shot = os.path.join(shots_dir, stem + ".png")
                problems, info = check_page(browser, page, shot, min_images)
                sizes = " ".join(f"{w}x{h}" for w, h in info["sizes"])
                if problems:
                    failed += 1
                    print(f"FAIL {page}\n  " + "\n  ".join(problems) + f"\n  screenshot: {shot}")
                else:
                    print(f"ok   {page}: {info['count']} images ({sizes}); screenshot {shot}")
        finally:
            browser.close()
    return 1 if failed else 0


def self_test(directory):
    """A page with a throwing script and a broken image must fail, a good one must pass."""
    d = pathlib.Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    png = ("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8DwHwAFBQIAX8jx0gAAAABJRU5ErkJggg==")
    (d / "good.html").write_text(f"<!doctype html><title>good</title><img alt='dot' src='data:image/png;base64,{png}'>")
    (d / "bad_script.html").write_text(f"<!doctype html><title>bad</title><img src='data:image/png;base64,{png}'>"
                                       "<script>undefinedFunction();</script>")
    (d / "bad_image.html").write_text("<!doctype html><title>bad</title><img alt='broken' src='data:image/png;base64,AAAA'>")
    (d / "missing_image.html").write_text("<!doctype html><title>bad</title><img alt='missing' src='no_such_file.png'>")
    (d / "broken_link.html").write_text(f"<!doctype html><title>bad</title><img src='data:image/png;base64,{png}'>"
                                        "<a href='no_such_report.html'>report</a>")
    shots = d / "screenshots"
    if run([str(d / "good.html")], str(shots), 1) == SKIP:
        return SKIP
    if run([str(d / "good.html")], str(shots), 1) != 0:
        print("self-test: a good page was reported as broken")
        return 1
    (d / "too_wide.html").write_text(f"<!doctype html><title>bad</title><img src='data:image/png;base64,{png}'>"
                                     "<table><tr>" + "<td>1.29945 +- 0.00190911</td>" * 120 + "</tr></table>")
    for bad in ("bad_script.html", "bad_image.html", "missing_image.html", "broken_link.html",
                "too_wide.html"):
        if run([str(d / bad)], str(shots), 1) != 1:
            print(f"self-test: {bad} was not caught")
            return 1
    print("self-test: the checker catches a script error, an undecodable and a missing image, "
          "a link to a missing file and a page wider than its window")
    return 0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pages", nargs="*")
    ap.add_argument("--screenshots", default="screenshots")
    ap.add_argument("--min-images", type=int, default=1)
    ap.add_argument("--self-test", metavar="DIR")
    a = ap.parse_args()
    if a.self_test:
        return self_test(a.self_test)
    if not a.pages:
        ap.error("no pages")
    return run(a.pages, a.screenshots, a.min_images)


if __name__ == "__main__":
    sys.exit(main())
