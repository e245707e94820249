"""A flood of page loads against ``prsa-app`` (not a test; issue 31): is an open page still
responsive, and does the server's memory stay bounded and come back?

1. ``prsa-app --no-browser`` is started; page A is opened in Debian's Chromium and its first
   design awaited.
2. Flood: ``--gets`` (default 200) plain ``GET /`` on 127.0.0.1, ``--concurrency`` (default 20)
   at a time, plus ``--browser-loads`` (default 12) real page loads in Chromium (each renders
   the placeholder and asks for a session: the gate builds at most 4 at a time and 16 open,
   and refuses the rest with one line). Meanwhile page A moves its Ms slider one step at a
   time; each step is timed from the key press to the re-tuned design on the page.
3. The flood's pages are closed; 30 s later (Bokeh's unused-session lifetime 10 s, checked
   every 5 s, then the collection) the server's memory is read again.

The server's resident memory (``VmRSS``; ``VmHWM`` for the peak) is read from ``/proc``.
Verdict lines: every slider step of page A within ``--max-step-s`` (default 2 s), the peak
below ``--max-rss-mb`` (default 1500 MB), and the memory after the sessions expired below
``--max-after-mb`` (default 900 MB). Exit 1 when one fails.

    python benchmarks/app_flood.py [--gets 200] [--concurrency 20] [--browser-loads 12]

``--fill`` instead opens pages one after the other in Chromium until the server refuses one
(16 open: ``prsa_ctrl.app.gate.MAX_LIVE_PAGES``) and prints the server's memory with them all
open, and again after they closed and their sessions expired.
"""

from __future__ import annotations

import argparse
import os
import queue
import re
import shutil
import subprocess
import sys
import threading
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--no-first-run", "--disable-sync"]


def _rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of ``pid`` in MB."""
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line.split(":")[0]] = int(line.split()[1]) / 1024.0
    return out["VmRSS"], out["VmHWM"]


def _get(url: str) -> int:
    with urllib.request.urlopen(url, timeout=120) as r:
        r.read()
        return r.status


def main() -> int:
    from playwright.sync_api import sync_playwright

    ap = argparse.ArgumentParser()
    ap.add_argument("--gets", type=int, default=200)
    ap.add_argument("--concurrency", type=int, default=20)
    ap.add_argument("--browser-loads", type=int, default=12)
    ap.add_argument("--max-step-s", type=float, default=2.0)
    ap.add_argument("--max-rss-mb", type=float, default=1500.0)
    ap.add_argument("--max-after-mb", type=float, default=900.0)
    ap.add_argument("--fill", action="store_true")
    a = ap.parse_args()
    if not (0 <= a.gets <= 1000 and 1 <= a.concurrency <= 50 and 0 <= a.browser_loads <= 60):
        ap.error("expected --gets in 0..1000, --concurrency in 1..50, --browser-loads in 0..60 (a bounded flood)")
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    proc = subprocess.Popen([sys.executable, "-m", "prsa_ctrl.app.cli", "--no-browser"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: lines.put(proc.stdout.readline()), daemon=True).start()
    url = lines.get(timeout=120).split()[2]
    assert url.startswith("http://127.0.0.1:"), url
    load0 = os.getloadavg()[0]
    ok = True
    if a.fill:
        try:
            return _fill(proc, url, exe, a.max_rss_mb, a.max_after_mb, load0)
        finally:
            proc.terminate()
            proc.wait()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=exe, args=ARGS)
            ctx = browser.new_context(viewport={"width": 1500, "height": 1300})
            page = ctx.new_page()
            page.set_default_timeout(120_000)
            t0 = time.perf_counter()
            page.goto(url)
            page.locator("[data-k='status'][data-landscape]").wait_for()
            print(f"page A ready in {time.perf_counter() - t0:.2f} s")
            rss0, _ = _rss_mb(proc.pid)

            # the flood: plain GETs in threads, browser loads from here (Playwright is single-threaded)
            peak = [rss0]
            stop = threading.Event()

            def sample():
                while not stop.is_set():
                    peak[0] = max(peak[0], _rss_mb(proc.pid)[0])
                    stop.wait(0.2)

            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()
            pool = ThreadPoolExecutor(a.concurrency)
            t_flood = time.perf_counter()
            gets = [pool.submit(_get, url) for _ in range(a.gets)]
            flood_ctx = browser.new_context(viewport={"width": 800, "height": 600})
            flood_ctx.set_default_timeout(300_000)
            flood_ctx.set_default_navigation_timeout(300_000)
            flood_pages = []
            for _ in range(a.browser_loads):
                fp = flood_ctx.new_page()
                fp.goto(url, wait_until="commit")
                flood_pages.append(fp)
            steps = []
            handle = page.locator(".prsa-ms .noUi-handle")
            k = 0
            while not all(g.done() for g in gets) or k < 6:
                handle.focus()
                key, want = ("ArrowRight", r"^1\.45$") if k % 2 == 0 else ("ArrowLeft", r"^1\.4$")
                t1 = time.perf_counter()
                page.keyboard.press(key)
                page.locator("[data-k='bound-ms']", has_text=re.compile(want)).wait_for()
                steps.append(time.perf_counter() - t1)
                k += 1
            codes = [g.result() for g in gets]
            t_gets = time.perf_counter() - t_flood
            built = refused = 0
            for fp in flood_pages:  # each ends built or refused
                fp.locator("[data-k='refused'], [data-k='opt-ms']").first.wait_for()
                refused += fp.locator("[data-k='refused']").count()
                built += fp.locator("[data-k='opt-ms']").count()
            t_all = time.perf_counter() - t_flood
            stop.set()
            sampler.join()
            _, hwm = _rss_mb(proc.pid)
            flood_ctx.close()
            pool.shutdown()
            time.sleep(30)  # unused-session lifetime 10 s + check interval 5 s + the collection, with margin
            page.keyboard.press("ArrowRight")  # page A still works after the flood's sessions went
            page.locator("[data-k='bound-ms']", has_text=re.compile(r"^1\.45$")).wait_for()
            rss_after, _ = _rss_mb(proc.pid)
            browser.close()
    finally:
        proc.terminate()
        proc.wait()
    print(f"flood: {a.gets} GET / ({a.concurrency} at a time; status {sorted(set(codes))}) answered in {t_gets:.1f} s; "
          f"{a.browser_loads} browser page loads: {built} built, {refused} refused with one line; all settled in "
          f"{t_all:.1f} s")
    print(f"page A during the flood: {len(steps)} Ms slider steps, each key press -> re-tuned design: "
          f"max {max(steps):.2f} s, median {sorted(steps)[len(steps) // 2]:.2f} s")
    print(f"server memory (RSS): {rss0:.0f} MB before the flood, peak {max(peak[0], hwm):.0f} MB (VmHWM {hwm:.0f}), "
          f"{rss_after:.0f} MB 30 s after the flood's pages closed")
    for what, good in ((f"every step of page A within {a.max_step_s:g} s", max(steps) <= a.max_step_s),
                       (f"peak memory below {a.max_rss_mb:g} MB", hwm <= a.max_rss_mb),
                       (f"memory after the sessions expired below {a.max_after_mb:g} MB", rss_after <= a.max_after_mb),
                       ("every GET answered 200", set(codes) == {200})):
        print(f"{'PASS' if good else 'FAIL'}: {what}")
        ok = ok and good
    print(f"load average (1 min): {load0:.2f} before, {os.getloadavg()[0]:.2f} after")
    return 0 if ok else 1


def _fill(proc, url: str, exe: str, max_rss_mb: float, max_after_mb: float, load0: float) -> int:
    """Open pages until one is refused; the server's memory with them all open and after."""
    from playwright.sync_api import sync_playwright

    rss0, _ = _rss_mb(proc.pid)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=ARGS)
        ctx = browser.new_context(viewport={"width": 1200, "height": 900})
        ctx.set_default_timeout(120_000)
        ctx.set_default_navigation_timeout(120_000)
        built = 0
        while built < 60:
            pg = ctx.new_page()
            pg.goto(url)
            pg.locator("[data-k='refused'], [data-k='status'][data-landscape]").first.wait_for()
            if pg.locator("[data-k='refused']").count():
                refused = pg.locator("[data-k='refused']").inner_text()
                break
            built += 1
            print(f"page {built} open: server RSS {_rss_mb(proc.pid)[0]:.0f} MB", flush=True)
        rss_full, hwm = _rss_mb(proc.pid)
        ctx.close()
        t_close = time.perf_counter()
        trail = []
        for wait in (5, 10, 15, 20, 30, 45):
            time.sleep(max(0.0, t_close + wait - time.perf_counter()))
            trail.append(f"{_rss_mb(proc.pid)[0]:.0f} MB at {wait} s")
        rss_after, _ = _rss_mb(proc.pid)
        browser.close()
    print("after closing: " + ", ".join(trail))
    print(f"{built} pages open, the next refused: {refused!r}")
    print(f"server memory (RSS): {rss0:.0f} MB with none, {rss_full:.0f} MB with {built} open "
          f"({(rss_full - rss0) / max(built, 1):.0f} MB a page; VmHWM {hwm:.0f} MB), {rss_after:.0f} MB 45 s after they "
          "closed")
    good = [(f"peak memory below {max_rss_mb:g} MB", hwm <= max_rss_mb),
            (f"memory after the sessions expired below {max_after_mb:g} MB", rss_after <= max_after_mb)]
    for what, g in good:
        print(f"{'PASS' if g else 'FAIL'}: {what}")
    print(f"load average (1 min): {load0:.2f} before, {os.getloadavg()[0]:.2f} after")
    return 0 if all(g for _, g in good) else 1


if __name__ == "__main__":
    sys.exit(main())
