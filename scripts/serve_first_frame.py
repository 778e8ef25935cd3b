"""Time from pressing Run in the ``ctgpp serve`` page to the first frame of the rollout drawn (issue 19).

Starts ``ctgpp serve`` on a free port, waits until its worker has loaded the simulator, then drives
Debian's headless chromium (selenium): picks the scene, types the sentence and, for each seed, sets it,
presses Run and reads the page's own clock (``window.ctgppTimings``: ``performance.now()`` at the
click and at the first frame drawn). The unguided comparison is off: it runs after the first frame and
would only delay the next seed. Prints one row per seed (the page's seconds, and the server's: queued,
Run to the guided rollout written, whole run) and the median, with the load average.

    python scripts/serve_first_frame.py --seeds 3 --duration 10
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any


def main() -> int:
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=raw)
    parser.add_argument("--scene", default="embedded:scene-0103", help="scene key (default: %(default)s)")
    parser.add_argument("--sentence", default="vehicle 1 should collide with vehicle 2",
                        help="the sentence (default: %(default)s)")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0, 1, ... (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=10.0,
                        help="simulated seconds (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("runs/serve-first-frame"),
                        help="the server's run folders (default: %(default)s)")
    args = parser.parse_args()

    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if k != "CTGPP_LLM_MODEL"}
    server = subprocess.Popen([sys.executable, "-m", "ctgpp.cli.main", "serve", "--port", str(port),
                               "--out", str(args.out)], env=env)
    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--window-size=1500,1000"):
        options.add_argument(arg)
    driver = None
    try:
        _wait_ready(url)
        driver = webdriver.Chrome(options=options, service=Service("/usr/bin/chromedriver"))
        wait = WebDriverWait(driver, 1800, poll_frequency=0.05)
        driver.get(url)
        wait.until(ec.element_to_be_clickable((By.CSS_SELECTOR, f"tr[data-key='{args.scene}']"))).click()
        wait.until(ec.text_to_be_present_in_element((By.ID, "status"), "vehicles at the start"))
        driver.find_element(By.ID, "compare").click()  # off
        _type(driver.find_element(By.ID, "duration"), f"{args.duration:g}")
        _type(driver.find_element(By.ID, "sentence"), args.sentence)
        load = [os.getloadavg()[0]]
        rows = []
        for seed in range(args.seeds):
            _type(driver.find_element(By.ID, "seed"), str(seed))
            wait.until(ec.element_to_be_clickable((By.ID, "run"))).click()
            wait.until(lambda d: d.execute_script("return window.ctgppTimings.first_frame !== undefined"))
            seconds = driver.execute_script("return window.ctgppTimings.seconds")
            wait.until(ec.text_to_be_present_in_element((By.ID, "status"), "Done"))
            job = json.loads(urllib.request.urlopen(f"{url}/api/runs").read())[0]
            status = json.loads(urllib.request.urlopen(f"{url}/api/runs/{job['id']}").read())
            rows.append((seed, seconds, status["seconds"]))
            server_s = status["seconds"]
            print(f"seed {seed}: first frame {seconds:.1f} s after Run (server: queued "
                  f"{server_s['queued']} s, to the rollout {server_s['to_rollout']} s, "
                  f"run {server_s['total']} s)", flush=True)
        load.append(os.getloadavg()[0])
    finally:
        if driver is not None:
            driver.quit()
        server.terminate()
        server.wait(timeout=60)
    firsts = [r[1] for r in rows]
    print(f"\n{args.scene}, '{args.sentence}', {args.duration:g} s episodes, {len(rows)} seeds: Run to first "
          f"frame median {statistics.median(firsts):.1f} s (min {min(firsts):.1f}, max {max(firsts):.1f}); "
          f"load average {load[0]:.1f} at the start, {load[1]:.1f} at the end")
    return 0


def _type(element: Any, text: str) -> None:
    element.clear()
    element.send_keys(text)


def _wait_ready(url: str, timeout_s: float = 600.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            health = json.loads(urllib.request.urlopen(f"{url}/api/health", timeout=5).read())
            if health["workers_ready"] and health["vocabulary_ready"]:
                return
        except OSError:
            pass
        time.sleep(0.5)
    raise SystemExit("ctgpp serve did not get ready")


if __name__ == "__main__":
    sys.exit(main())
