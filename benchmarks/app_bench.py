"""Benchmark of prsa-app in Debian's Chromium (not a test): medians of 5.

- start: ``prsa-app --no-browser`` launched -> first full page (readout and landscape drawn);
- slider: Ms slider moved one step -> the re-tuned design is on the page;
- drag: the mouse moved one step while dragging on the landscape -> the manual design's row
  shows the new gains;
- generic: the generic tab opened -> the default plant tuned (a child process started first),
  and an Ms bound typed there -> the re-tuned design.

The load average (1 min) is printed before and after: the machine is shared. The medians, every
run and the load averages go to ``OUT/app_bench.json`` (``--out``, default ``bench-results``).

    python benchmarks/app_bench.py [--repeats 5] [--out DIR]
    python benchmarks/app_bench.py --fast    # one of each (a check that the file runs; CI)
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
from pathlib import Path

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

    ap = argparse.ArgumentParser(prog="benchmarks/app_bench.py", description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=None, help="starts and steps of each kind (default 5; 1 with --fast)")
    ap.add_argument("--fast", action="store_true", help="one of each: a check that the file runs (the figures mean "
                    "little)")
    ap.add_argument("--out", default="bench-results", help="folder for app_bench.json (created if missing)")
    args = ap.parse_args()
    n = args.repeats if args.repeats is not None else (1 if args.fast else 5)
    if not 1 <= n <= 50:
        ap.error(f"--repeats {n}: expected 1..50")
    from prsa_ctrl.io.output import OutputError, check_directory, make_directory

    try:
        check_directory(args.out, "--out")
        make_directory(args.out, "--out")
    except OutputError as exc:
        ap.error(str(exc))
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        ap.error("no chromium on PATH; expected Debian's chromium (apt-get install chromium)")
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
    load1 = os.getloadavg()[0]
    print(f"load average (1 min): {load0:.2f} before, {load1:.2f} after")
    from prsa_ctrl.cli.common import write_json_atomic

    runs = {"start_s": starts, "slider_s": slides, "drag_s": drags, "generic_open_s": g_open, "generic_bound_s": g_bound}
    out = Path(args.out) / "app_bench.json"
    write_json_atomic(out, {"fast": bool(args.fast), "repeats": n, "statistic": "median",
                            "median_s": {k: statistics.median(v) for k, v in runs.items()}, "runs_s": runs,
                            "load_average_1min": [load0, load1]})
    print(f"results: {out}")


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
