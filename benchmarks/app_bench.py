"""Benchmark of prsa-app in Debian's Chromium (not a test): medians of 5.

- start: ``prsa-app --no-browser`` launched -> first full page (readout and landscape drawn);
- slider: Ms slider moved one step -> the re-tuned design is on the page.

    python benchmarks/app_bench.py [--repeats 5]
"""

from __future__ import annotations

import argparse
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
    starts, slides = [], []
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
                page.close()
            finally:
                proc.terminate()
                proc.wait()
        browser.close()
    print(f"app start -> first full page: median {statistics.median(starts):.2f} s over {len(starts)} starts "
          f"(min {min(starts):.2f}, max {max(starts):.2f})")
    print(f"Ms slider step -> re-tuned design on the page: median {statistics.median(slides):.3f} s over "
          f"{len(slides)} changes (min {min(slides):.3f}, max {max(slides):.3f})")


if __name__ == "__main__":
    main()
