"""Benchmark of prsa-app in Debian's Chromium (not a test): medians of 5.

- start: ``prsa-app --no-browser`` launched -> first full page (readout and landscape drawn);
- slider: Ms slider moved one step -> the re-tuned design is on the page;
- drag: the mouse moved one step while dragging on the landscape -> the manual design's row
  shows the new gains;
- generic: the generic tab opened -> the default plant tuned (a child process started first),
  and an Ms bound typed there -> the re-tuned design.

The load average (1 min) is printed before and after: the machine is shared.

    python benchmarks/app_bench.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import queue
import re
import shutil
import statistics
import subprocess
import sys
import threading
import time

ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--no-first-run", "--disable-sync"]


def _start_server():
    proc = subprocess.Popen([sys.executable, "-m", "prsa_ctrl.app.cli", "--no-browser"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    q: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: q.put(proc.stdout.readline()), daemon=True).start()
    return proc, q.get(timeout=120).split()[2]


def main() -> None:
    from playwright.sync_api import sync_playwright

    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    n = ap.parse_args().repeats
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    starts, slides, drags, g_open, g_bound = [], [], [], [], []
    load0 = os.getloadavg()[0]
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=ARGS)
        for i in range(n):
            t0 = time.perf_counter()
            proc, url = _start_server()
            try:
                page = browser.new_page(viewport={"width": 1500, "height": 1300})
                page.set_default_timeout(60_000)
                page.goto(url)
                page.locator("[data-k='status'][data-landscape]").wait_for()
                page.locator("[data-k='opt-ms']").wait_for()
                starts.append(time.perf_counter() - t0)
                handle = page.locator(".prsa-ms .noUi-handle")
                handle.focus()
                for k in range(n):
                    key, want = ("ArrowRight", r"^1\.45$") if k % 2 == 0 else ("ArrowLeft", r"^1\.4$")
                    t1 = time.perf_counter()
                    page.keyboard.press(key)
                    page.locator("[data-k='bound-ms']", has_text=re.compile(want)).wait_for()
                    slides.append(time.perf_counter() - t1)
                drags += _drag_steps(page, n)
                page.get_by_text("Generic plant (transfer function)").click()
                t1 = time.perf_counter()
                page.locator("[data-k='g-state'][data-state='done']").wait_for()
                g_open.append(time.perf_counter() - t1)
                for k in range(n):
                    ms = "1.25" if k % 2 == 0 else "1.4"
                    box = page.locator(".prsa-g-ms input")
                    box.fill(ms)
                    t1 = time.perf_counter()
                    box.press("Enter")
                    page.locator(f"[data-k='g-state'][data-state='done'][data-sig^='1/(4s+1)|0|iae|pi|{ms}|']").wait_for()
                    g_bound.append(time.perf_counter() - t1)
                page.close()
            finally:
                proc.terminate()
                proc.wait()
        browser.close()
    print(f"app start -> first full page: median {statistics.median(starts):.2f} s over {len(starts)} starts "
          f"(min {min(starts):.2f}, max {max(starts):.2f})")
    for what, xs in (("Ms slider step -> re-tuned design on the page", slides),
                     ("drag step on the landscape -> manual design's row updated", drags),
                     ("generic tab opened -> 1/(4s+1) tuned (child process started)", g_open),
                     ("generic Ms bound typed -> re-tuned design", g_bound)):
        print(f"{what}: median {statistics.median(xs):.3f} s over {len(xs)} (min {min(xs):.3f}, max {max(xs):.3f})")
    print(f"load average (1 min): {load0:.2f} before, {os.getloadavg()[0]:.2f} after")


def _drag_steps(page, n: int) -> list[float]:
    """Press on the landscape and move in ``n`` steps; each: time until the manual row shows
    new gains."""
    box = page.locator(".prsa-landscape").bounding_box()
    x0, y0 = box["x"] + 0.35 * box["width"], box["y"] + 0.65 * box["height"]
    page.mouse.move(x0, y0)
    page.mouse.down()
    out, last = [], None
    for k in range(1, n + 2):
        t1 = time.perf_counter()
        page.mouse.move(x0 + 0.03 * k * box["width"], y0 - 0.03 * k * box["height"])
        page.locator("[data-k='man-kp']").wait_for()
        while True:  # polled through Playwright (a few ms a round trip)
            now = (page.locator("[data-k='man-kp']").inner_text(), page.locator("[data-k='man-ki']").inner_text())
            if now != last:
                break
        if k > 1:  # the first move starts the drag
            out.append(time.perf_counter() - t1)
        last = now
    page.mouse.up()
    return out


if __name__ == "__main__":
    main()
