"""Time from pressing Run in the ``ctgpp serve`` page to the first simulated frame drawn (issues 19, 38).

Starts one ``ctgpp serve`` per source tree given (``--src DIR``, its ``src`` put first on PYTHONPATH;
none: the installed package) on free ports, waits until their workers are ready, then drives Debian's
headless chromium (selenium), one window per server: picks the scene, types the sentence, and runs
one short warm-up run (1 s, not timed) on each. Then, for each seed, the servers in turn (interleaved,
so that the machine's load falls on every version alike): sets the seed, presses Run and reads the
page's own clock (``window.ctgppTimings``: ``performance.now()`` at the click and at the first frame
drawn), then cancels the rest of the run and waits until it has stopped and the server's worker is
ready (a worker that does not stop within 10 s of a cancel is restarted, and warms up again). The
unguided comparison is off (it runs after the guided episode). Prints one row per run (the page's
seconds, and the server's: queued, to the first streamed frame where the server streams, to the
guided rollout) and each version's median, with the load average (1 min) before and after.

    python scripts/serve_first_frame.py --seeds 5 --src /work/base --src .
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
    parser.add_argument("--seeds", type=int, default=5, help="seeds 0, 1, ... (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=10.0,
                        help="simulated seconds (default: %(default)s)")
    parser.add_argument("--src", type=Path, action="append", default=[],
                        help="a source tree to serve (repeatable; default: the installed package)")
    parser.add_argument("--out", type=Path, default=Path("runs/serve-first-frame"),
                        help="the servers' run folders go under it (default: %(default)s)")
    args = parser.parse_args()
    trees: list[Path | None] = list(args.src) or [None]
    for tree in trees:
        if tree is not None and not (tree / "src" / "ctgpp").is_dir():
            raise SystemExit(f"--src {tree}: no src/ctgpp there")

    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    servers: list[tuple[str, str, subprocess.Popen[bytes]]] = []
    drivers: list[Any] = []
    rows: dict[str, list[float]] = {}
    try:
        for k, tree in enumerate(trees):
            label = "installed" if tree is None else str(tree)
            env = {key: v for key, v in os.environ.items() if key != "CTGPP_LLM_MODEL"}
            if tree is not None:
                src = str((tree / "src").resolve())
                env["PYTHONPATH"] = os.pathsep.join(p for p in (src, env.get("PYTHONPATH")) if p)
            port = _free_port()
            process = subprocess.Popen([sys.executable, "-m", "ctgpp.cli.main", "serve", "--port", str(port),
                                        "--out", str(args.out / f"server-{k}")], env=env)
            servers.append((label, f"http://127.0.0.1:{port}", process))
            rows[label] = []
        for _label, url, _process in servers:
            _wait_ready(url)
        options = webdriver.ChromeOptions()
        options.binary_location = "/usr/bin/chromium"
        for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                    "--window-size=1500,1000"):
            options.add_argument(arg)
        for _label, url, _process in servers:
            driver = webdriver.Chrome(options=options, service=Service("/usr/bin/chromedriver"))
            drivers.append(driver)
            _open(driver, url, args.scene, args.sentence)
            _run(driver, url, seed=0, duration=1.0)  # warm-up, not timed
        load = [os.getloadavg()[0]]
        for seed in range(args.seeds):
            for (label, url, _process), driver in zip(servers, drivers, strict=True):
                seconds, server_s = _run(driver, url, seed, args.duration)
                rows[label].append(seconds)
                print(f"{label} seed {seed}: first frame {seconds:.2f} s after Run (server: queued "
                      f"{server_s.get('queued')} s, to the first frame {server_s.get('to_first_frame')} s, "
                      f"to the rollout {server_s.get('to_rollout')} s; load {os.getloadavg()[0]:.1f})",
                      flush=True)
        load.append(os.getloadavg()[0])
    finally:
        for driver in drivers:
            driver.quit()
        for _label, _url, process in servers:
            process.terminate()
            process.wait(timeout=60)
    print(f"\n{args.scene}, '{args.sentence}', {args.duration:g} s episodes, seeds 0-{args.seeds - 1}, "
          f"interleaved; load average {load[0]:.1f} at the start, {load[1]:.1f} at the end")
    for label, firsts in rows.items():
        print(f"{label}: Run to first frame median {statistics.median(firsts):.2f} s "
              f"(min {min(firsts):.2f}, max {max(firsts):.2f}; {', '.join(f'{s:.2f}' for s in firsts)})")
    return 0


def _open(driver: Any, url: str, scene: str, sentence: str) -> None:
    """Load the page, pick ``scene``, turn the comparison off, type ``sentence``."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    wait = WebDriverWait(driver, 600, poll_frequency=0.05)
    driver.get(url)
    wait.until(ec.element_to_be_clickable((By.CSS_SELECTOR, f"tr[data-key='{scene}']"))).click()
    wait.until(ec.text_to_be_present_in_element((By.ID, "status"), "vehicles at the start"))
    wait.until(ec.element_to_be_clickable((By.ID, "run")))
    driver.find_element(By.ID, "compare").click()  # off
    _type(driver.find_element(By.ID, "sentence"), sentence)


def _run(driver: Any, url: str, seed: int, duration: float) -> tuple[float, dict[str, Any]]:
    """Press Run with ``seed`` and ``duration``: seconds to the first frame drawn, and the server's
    timings; the rest of the run is cancelled and waited for."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    wait = WebDriverWait(driver, 1800, poll_frequency=0.02)
    _type(driver.find_element(By.ID, "seed"), str(seed))
    _type(driver.find_element(By.ID, "duration"), f"{duration:g}")
    wait.until(ec.element_to_be_clickable((By.ID, "run"))).click()
    wait.until(lambda d: d.execute_script("return window.ctgppTimings.first_frame !== undefined"))
    seconds = float(driver.execute_script("return window.ctgppTimings.seconds"))
    job = json.loads(urllib.request.urlopen(f"{url}/api/runs").read())[0]
    request = urllib.request.Request(f"{url}/api/runs/{job['id']}/cancel", data=b"{}", method="POST",
                                     headers={"Content-Type": "application/json"})
    urllib.request.urlopen(request).read()
    while True:
        status = json.loads(urllib.request.urlopen(f"{url}/api/runs/{job['id']}").read())
        if status["state"] in ("done", "failed", "refused", "cancelled"):
            break
        time.sleep(0.1)
    _wait_ready(url)  # a worker restarted after a slow cancel is warm again before the next run
    wait.until(ec.element_to_be_clickable((By.ID, "run")))
    return seconds, status["seconds"]


def _type(element: Any, text: str) -> None:
    element.clear()
    element.send_keys(text)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _wait_ready(url: str, timeout_s: float = 900.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            health = json.loads(urllib.request.urlopen(f"{url}/api/health", timeout=5).read())
            if health["workers_ready"] and health["vocabulary_ready"]:
                return
        except OSError:
            pass
        time.sleep(0.5)
    raise SystemExit(f"ctgpp serve at {url} did not get ready")


if __name__ == "__main__":
    sys.exit(main())
