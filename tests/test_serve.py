"""``ctgpp serve`` (issue 19): the JSON API against the real server (``ctgpp serve`` started as a
process on a free port, spoken to over HTTP), and the page in a real headless browser (Debian's
chromium driven by selenium): pick scene-0103, type a sentence, run it, see the animation advance
and the verdict appear.

The server runs with a language model configured (an address where nothing listens, a made-up key):
the page offers it by name, and the key appears in no answer. Episodes are short (1-2 s).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from ctgpp.cli.main import main
from tests.support.data import NGSIM

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
SECRET_KEY = "sk-test-serve-5f1c0b7e-never-shown"
LLM_MODEL = "local-test-model"
SENTENCE = "vehicle 1 should collide with vehicle 2"
THREE_POINT_TURN = "the red car should do a three-point turn quickly"
PEACHTREE = "USA_Peach-4_1_T-1"  # 7.0 s of real NGSIM log: episodes up to 6 s
START_TIMEOUT_S = 900.0  # limits, not expectations: torch loads in three processes, and the project
RUN_TIMEOUT_S = 900.0  # machine is often shared by a training run and several test runs (load 10-13)


class Server:
    """A running ``ctgpp serve`` and a small HTTP client for it."""

    def __init__(self, url: str, out: Path, process: subprocess.Popen[str]) -> None:
        self.url, self.out, self.process = url, out, process
        self.bodies: list[str] = []  # every answer, to look for the key in

    def request(self, path: str, body: Any = None, raw: bytes | None = None) -> tuple[int, Any]:
        data = raw if raw is not None else None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method="GET" if data is None else "POST",
                                     headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=60) as answer:
                status, text = answer.status, answer.read().decode("utf-8", "replace")
        except urllib.error.HTTPError as err:
            status, text = err.code, err.read().decode("utf-8", "replace")
        self.bodies.append(text)
        try:
            return status, json.loads(text)
        except ValueError:
            return status, text

    def get(self, path: str) -> Any:
        status, data = self.request(path)
        assert status == 200, (path, status, data)
        return data

    def submit(self, **fields: Any) -> dict[str, Any]:
        status, job = self.request("/api/runs", {"scene": "embedded:scene-0103", **fields})
        assert status == 201, job
        return job

    def wait(self, job_id: str, until: tuple[str, ...] = ("done", "failed", "refused", "cancelled"),
             timeout: float = RUN_TIMEOUT_S, **matching: Any) -> dict[str, Any]:
        """Poll the run until its state is one of ``until`` and its fields equal ``matching``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            job = self.get(f"/api/runs/{job_id}")
            if job["state"] in until and all(job.get(k) == v for k, v in matching.items()):
                return job
            if job["state"] in ("done", "failed", "refused", "cancelled"):
                break
            time.sleep(0.3)
        raise AssertionError(f"run {job_id} is {job['state']} ({job['phase']}): {job['message']}")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """``ctgpp serve`` with a --data set (one real NGSIM scenario, converted) and a language model."""
    root = tmp_path_factory.mktemp("serve")
    shutil.copy(NGSIM / "Peachtree" / f"{PEACHTREE}.xml", root / f"{PEACHTREE}.xml")
    assert main(["data", "convert", str(root), str(root / "ngsim")]) == 0
    out = root / "runs"
    port = _free_port()
    env = {**os.environ, "CTGPP_LLM_MODEL": LLM_MODEL, "OPENAI_API_KEY": SECRET_KEY,
           "OPENAI_BASE_URL": f"http://127.0.0.1:{_free_port()}/v1"}  # nothing listens there
    process = subprocess.Popen(
        [sys.executable, "-m", "ctgpp.cli.main", "serve", "--port", str(port), "--out", str(out),
         "--data", str(root / "ngsim")],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    served = Server(f"http://127.0.0.1:{port}", out, process)
    deadline = time.monotonic() + START_TIMEOUT_S
    try:
        while True:
            assert process.poll() is None, process.stdout.read() if process.stdout else ""
            try:
                health = served.get("/api/health")
                if health["workers_ready"] and health["vocabulary_ready"]:
                    break
            except (urllib.error.URLError, ConnectionError):
                pass
            assert time.monotonic() < deadline, "ctgpp serve did not get ready"
            time.sleep(0.5)
        yield served
    finally:
        process.terminate()
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


# --- the API ------------------------------------------------------------------------------------


def test_scenes_and_a_scene_drawn_as_data(server: Server) -> None:
    scenes = {s["key"]: s for s in server.get("/api/scenes")}
    entry = scenes["embedded:scene-0103"]
    assert (entry["map"], entry["vehicles"], entry["split"]) == ("boston-seaport", 61, "mini_val")
    assert len(scenes) == 11 and entry["max_duration_s"] == 18.5
    ngsim = scenes[f"ngsim:{PEACHTREE}"]  # the --data set beside the embedded scenes
    assert (ngsim["set"], ngsim["duration_s"], ngsim["max_duration_s"]) == ("ngsim", 7.0, 6.0)
    view = server.get("/api/scenes/embedded:scene-0103?duration_s=2")
    numbered = sorted(a["number"] for a in view["agents"] if a["number"] >= 0)
    assert numbered == list(range(view["vehicles"])) and view["vehicles"] == 12  # as `ctgpp show` has them
    assert any(a["moving"] for a in view["agents"]) and any(not a["moving"] for a in view["agents"])
    assert view["drivable"]["png"].startswith("data:image/png;base64,") and len(view["lanes"]) > 100
    assert server.request("/api/scenes/embedded:scene-9999")[0] == 404
    assert server.request("/api/scenes/..%2F..%2Fetc")[0] == 404


def test_options_name_the_model_but_never_its_key(server: Server) -> None:
    options = server.get("/api/options")
    assert options["llm"] == {"model": LLM_MODEL}
    assert options["policies"][0] == "ctgpp" and "constvel" in options["policies"]
    assert SENTENCE in options["phrasings"]
    page = server.get("/")
    assert "<canvas" in page and not re.search(r"(src|href)=\"(https?:)?//", page)  # nothing from elsewhere


def test_a_run_gives_a_rollout_verdicts_metrics_and_files(server: Server) -> None:
    job = server.submit(sentence=SENTENCE, duration_s=2, policy="constvel", exports=["scenarionet"])
    assert job["state"] in ("queued", "running")
    done = server.wait(job["id"])
    assert done["state"] == "done", done["message"]
    record = done["record"]
    assert record["scene"] == "scene-0103" and record["duration_s"] == 2.0
    assert record["query"]["text"] == SENTENCE and [p["text"] for p in record["query"]["parts"]]
    assert record["query"]["path"] == "offline query compiler" and "collision" in record["query"]["code"]
    assert done["baseline"] is None  # constvel is not guided: nothing to compare
    playback = server.get(f"/api/runs/{job['id']}/playback")
    assert playback["time_s"][playback["current"]] == 0.0 and playback["time_s"][-1] == 2.0
    numbered = [a for a in playback["agents"] if a["number"] >= 0]
    assert len(numbered) == 12 and all(len(a["x"]) == len(playback["time_s"]) for a in numbered)
    expected = {"metrics.json", "rollout.parquet", "playback.json", "sd_ctgpp_scene-0103.pkl"}
    assert set(done["files"]) >= expected
    metrics = server.get(f"/api/runs/{job['id']}/files/metrics.json")
    assert metrics["query"]["satisfied"] == record["query"]["satisfied"]
    folder = server.out / done["folder"]
    assert (folder / "rollout.parquet").is_file()
    assert json.loads((folder / "request.json").read_text())["seed"] == 0
    assert server.request(f"/api/runs/{job['id']}/files/request.json.bak")[0] == 404
    assert server.request(f"/api/runs/{job['id']}/files/..%2Fmetrics.json")[0] == 404
    assert done["command"].startswith(f"ctgpp simulate '{SENTENCE}' --scene scene-0103")


def test_a_run_on_a_data_set_of_the_server(server: Server) -> None:
    job = server.submit(scene=f"ngsim:{PEACHTREE}", sentence="vehicle 2 should stop", duration_s=5,
                        policy="constvel")
    done = server.wait(job["id"])
    assert done["state"] == "done", done["message"]
    assert (done["record"]["scene"], done["record"]["duration_s"]) == (PEACHTREE, 5.0)
    assert "--data" in done["command"] and "--duration 5" in done["command"]


def test_a_refused_sentence_gets_the_closest_phrasings(server: Server) -> None:
    status, answer = server.request("/api/runs", {"scene": "embedded:scene-0103",
                                                  "sentence": "vehicle 3 should fly to the moon"})
    assert status == 422 and answer["refused"] is True
    assert len(answer["suggestions"]) == 3 and "no supported phrasing matches" in answer["message"]
    # the page lists the suggestions: the message does not list them again
    assert "Closest supported phrasings" not in answer["message"]
    assert not any(s in answer["message"] for s in answer["suggestions"])
    # a manoeuvre the vocabulary lacks: refused by name, with no suggestion (the page shows no list)
    status, answer = server.request("/api/runs", {"scene": "embedded:scene-0103",
                                                  "sentence": THREE_POINT_TURN})
    assert status == 422 and answer["refused"] is True and answer["suggestions"] == []
    assert "three-point turn" in answer["message"]
    status, answer = server.request("/api/runs", {"scene": "embedded:scene-0103",
                                                  "sentence": "vehicle 40 should stop"})
    assert status == 422 and "vehicles 0-11" in answer["message"]


@pytest.mark.parametrize(
    "body, status, words",
    [
        ({"scene": "embedded:scene-0103", "path": "/etc/passwd"}, 422, "path"),
        ({"scene": "embedded:scene-0103", "sentence": "x" * 301}, 422, "sentence"),
        ({"scene": "embedded:scene-0103", "seed": -1}, 422, "seed"),
        ({"scene": "embedded:scene-0103", "duration_s": 19}, 422, "too short"),
        ({"scene": "/etc/passwd"}, 422, "scene"),
        ({"scene": "embedded:scene-0103", "policy": "__import__('os')"}, 422, "policy"),
        ({"scene": "embedded:scene-0103", "policy": "nope"}, 422, "unknown policy"),
        ({"scene": "embedded:scene-0103", "exports": ["../x"]}, 422, "exports"),
        ({"scene": "ngsim:USA_1"}, 404, "unknown scene"),
    ],
)
def test_only_scene_keys_sentences_and_numbers_are_taken(
    server: Server, body: dict[str, Any], status: int, words: str
) -> None:
    got, answer = server.request("/api/runs", body)
    assert got == status and words in answer["message"], answer
    assert "Traceback" not in answer["message"] and "\n" not in answer["message"]


def test_request_size_is_bounded(server: Server) -> None:
    status, answer = server.request("/api/runs", raw=b'{"scene": "' + b"a" * 10_000 + b'"}')
    assert status == 413 and "larger than" in answer["message"]


@pytest.mark.model
def test_runs_queue_are_cancelled_and_the_server_answers_meanwhile(server: Server) -> None:
    long = server.submit(sentence=SENTENCE, duration_s=10, compare=False)
    waiting = server.submit(sentence="vehicle 2 should stop", duration_s=1, policy="constvel")
    after = server.submit(sentence="vehicle 2 should stop", duration_s=1, policy="constvel")
    server.wait(long["id"], until=("running",), phase="guided")
    assert server.get(f"/api/runs/{waiting['id']}")["position"] == 1
    assert server.get(f"/api/runs/{after['id']}")["position"] == 2
    # the server answers while the run computes: listing, drawing a scene, queueing
    assert len(server.get("/api/scenes")) == 11
    assert server.get("/api/scenes/embedded:scene-0553?duration_s=3")["vehicles"] > 0
    assert server.get(f"/api/runs/{long['id']}")["state"] == "running"
    cancelled = server.request(f"/api/runs/{waiting['id']}/cancel", {})[1]
    assert cancelled["state"] == "cancelled"
    server.request(f"/api/runs/{long['id']}/cancel", {})
    assert server.wait(long["id"])["state"] == "cancelled"
    assert server.wait(after["id"])["state"] == "done"  # the worker goes on with the next
    folders = {server.get(f"/api/runs/{j['id']}")["folder"] for j in (long, waiting, after)}
    assert len(folders) == 3


@pytest.mark.model
def test_frames_stream_as_each_replan_finishes(server: Server) -> None:
    """The guided episode's frames come while it runs (before its rollout exists), the first after
    the first re-plan, and are the steps of the finished rollout."""
    job = server.submit(sentence=SENTENCE, duration_s=4, compare=False)
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while True:
        streamed = server.get(f"/api/runs/{job['id']}/frames?since=0")
        status = server.get(f"/api/runs/{job['id']}")
        if streamed["count"] > 0:
            break
        assert status["state"] in ("queued", "running") and time.monotonic() < deadline, status
        time.sleep(0.05)
    header = streamed["header"]
    assert header["current"] == 30 and header["steps"] == 31 + 40 and header["dt_s"] == 0.1
    assert not status["has_rollout"] and status["frames"] >= streamed["count"]
    assert streamed["count"] < header["steps"]  # the run is not over: 8 re-plans of 5 steps
    assert sum(a["number"] >= 0 for a in header["agents"]) == 12
    later = server.get(f"/api/runs/{job['id']}/frames?since={streamed['count']}")
    assert later["start"] == streamed["count"]
    done = server.wait(job["id"])
    assert done["state"] == "done" and done["seconds"]["to_first_frame"] < done["seconds"]["to_rollout"]
    every = server.get(f"/api/runs/{job['id']}/frames?since=0")
    assert every["count"] == header["steps"] == done["frames"]
    playback = server.get(f"/api/runs/{job['id']}/playback")
    final = {a["number"]: a for a in playback["agents"] if a["number"] >= 0}
    for j, agent in enumerate(header["agents"]):
        if agent["number"] < 0:
            continue
        for k, frame in enumerate(every["frames"]):
            want = final[agent["number"]]
            got = frame[j]
            assert (got is None) == (want["x"][k] is None), (agent["number"], k)
            if got is not None:
                assert got[:2] == [want["x"][k], want["y"][k]], (agent["number"], k)


@pytest.mark.model
def test_the_model_is_loaded_once_per_worker_when_the_server_starts(server: Server) -> None:
    """Two runs (guards on, then off) on the one worker use the same model object of the same
    process, loaded before either was submitted."""
    before = time.time()
    first = server.wait(server.submit(sentence="vehicle 2 should stop", duration_s=1, compare=False)["id"])
    second = server.wait(server.submit(sentence="vehicle 2 should stop", duration_s=1, compare=False,
                                       guards=False)["id"])
    assert first["state"] == second["state"] == "done"
    assert first["model"] == second["model"] and first["model"]["loaded_at"] < before
    assert first["model"]["pid"] != server.process.pid  # the worker's process, not the server's


@pytest.mark.model
def test_the_unguided_comparison_gives_way_to_a_waiting_run(server: Server) -> None:
    """A run submitted while another simulates its unguided comparison does not wait for it: the
    comparison stops at its next re-plan (said in the baseline), the guided run it made is kept."""
    first = server.submit(sentence=SENTENCE, duration_s=4, compare=True)
    server.wait(first["id"], until=("running",), phase="unguided")
    second = server.submit(sentence="vehicle 2 should stop", duration_s=1, policy="constvel")
    done = server.wait(first["id"])
    assert done["state"] == "done" and done["record"] is not None and done["has_rollout"]
    assert "another run was waiting" in done["baseline"]["skipped"]
    assert "unguided.json" not in done["files"]
    assert server.wait(second["id"])["state"] == "done"


@pytest.mark.slow
def test_a_language_model_run_keeps_the_key_on_the_server(server: Server) -> None:
    """The model is unreachable: the run falls back to the offline compiler and says so."""
    job = server.submit(sentence="vehicle 2 should stop", duration_s=1, policy="constvel", llm=True)
    done = server.wait(job["id"])
    assert done["state"] == "done", done["message"]
    assert "offline query compiler (fallback)" == done["record"]["query"]["path"]
    server.get("/api/runs")
    assert server.bodies and not any(SECRET_KEY in body for body in server.bodies)


def test_a_failed_run_is_one_line(tmp_path: Path) -> None:
    from ctgpp.serve.models import WorkerModels
    from ctgpp.serve.worker import RunSpec, run_safely

    spec = RunSpec(1, str(tmp_path / "run"), "scene-9999", None, "", 0, 1.0, "constvel", "on", False, False)
    kind, payload = run_safely(spec, None, lambda kind, payload: None, lambda: False, WorkerModels())
    assert kind == "error" and "\n" not in payload["message"] and "Traceback" not in payload["message"]


# --- the page in a real browser -----------------------------------------------------------------


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not CHROMIUM.is_file() or not CHROMEDRIVER.is_file():
        pytest.skip("the browser test needs Debian's chromium and chromium-driver "
                    "(apt-get install chromium chromium-driver; .ci/run installs them)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--window-size=1500,1000", "--force-device-scale-factor=1"):
        options.add_argument(arg)
    driver = webdriver.Chrome(options=options, service=Service(str(CHROMEDRIVER)))
    try:
        yield driver
    finally:
        driver.quit()


def _screenshot(driver: Any, tmp_path: Path, name: str) -> None:
    """Save a screenshot under tmp_path, and into $CTGPP_SCREENSHOTS when set (the README's pictures)."""
    path = tmp_path / name
    driver.save_screenshot(str(path))
    folder = os.environ.get("CTGPP_SCREENSHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(folder) / name)


def _hover(driver: Any, number: int) -> str:
    """Move the mouse onto vehicle ``number`` on the canvas; the tooltip's text."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    driver.execute_script("window.scrollTo(0, 0)")  # the offsets below are of the page unscrolled
    canvas = driver.find_element(By.ID, "canvas")
    point = driver.execute_script("return window.ctgppVehicleAt(arguments[0])", number)
    dx, dy = point["x"] - canvas.size["width"] / 2, point["y"] - canvas.size["height"] / 2
    ActionChains(driver).move_to_element_with_offset(canvas, int(dx), int(dy)).perform()
    tooltip = driver.find_element(By.ID, "tooltip")
    assert tooltip.is_displayed()
    return str(tooltip.text)


@pytest.mark.model
def test_the_page_runs_a_sentence_and_plays_it(server: Server, browser: Any, tmp_path: Path) -> None:
    """Pick scene-0103, hover a vehicle, type a sentence the compiler refuses (the closest phrasings
    appear), then one it takes, run it: the first frame is drawn, the animation advances, the verdict
    and the results appear. With $CTGPP_SCREENSHOTS the episode is 4 s (the collision happens)."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    wait = WebDriverWait(browser, RUN_TIMEOUT_S, poll_frequency=0.1)
    browser.get(server.url)
    row = wait.until(ec.element_to_be_clickable((By.CSS_SELECTOR, "tr[data-key='embedded:scene-0103']")))
    duration = browser.find_element(By.ID, "duration")
    duration.clear()
    duration.send_keys("4" if os.environ.get("CTGPP_SCREENSHOTS") else "2")
    row.click()
    wait.until(ec.text_to_be_present_in_element((By.ID, "status"), "12 vehicles at the start"))
    wait.until(ec.element_to_be_clickable((By.ID, "run")))
    assert LLM_MODEL in browser.find_element(By.ID, "llm-option").text
    tip = _hover(browser, 1)
    assert tip.startswith("vehicle 1 · vehicle · ") and "m/s · moving at the start" in tip
    sentence = browser.find_element(By.ID, "sentence")
    sentence.send_keys("vehicle 3 should fly to the moon")
    browser.find_element(By.ID, "run").click()
    refusal = wait.until(ec.visibility_of_element_located((By.ID, "refusal")))
    suggestions = [li.text for li in browser.find_elements(By.CSS_SELECTOR, "#suggestions li")]
    assert len(suggestions) == 3 and browser.find_element(By.ID, "suggestions-wrap").is_displayed()
    assert all(refusal.text.count(s) == 1 for s in suggestions)  # each shown once
    _screenshot(browser, tmp_path, "serve-refused.png")
    sentence.send_keys(" now")  # a new sentence: the refusal of the old one goes
    assert not refusal.is_displayed() and not browser.find_elements(By.CSS_SELECTOR, "#suggestions li")
    sentence.clear()
    sentence.send_keys(THREE_POINT_TURN)
    browser.find_element(By.ID, "run").click()
    wait.until(ec.visibility_of_element_located((By.ID, "refusal")))
    assert "three-point turn" in browser.find_element(By.ID, "refusal-message").text
    assert not browser.find_element(By.ID, "suggestions-wrap").is_displayed()  # no empty list

    sentence.clear()
    sentence.send_keys(SENTENCE)
    browser.find_element(By.ID, "run").click()
    canvas = browser.find_element(By.ID, "canvas")
    wait.until(lambda d: int(canvas.get_attribute("data-frame")) >= 0)  # the first frame is drawn
    timings = browser.execute_script("return window.ctgppTimings")
    assert timings["seconds"] > 0
    first = int(canvas.get_attribute("data-frame"))
    wait.until(lambda d: int(canvas.get_attribute("data-frame")) > first)  # the animation advances
    verdict = wait.until(lambda d: d.find_element(By.CSS_SELECTOR, "#verdict.yes, #verdict.no"))
    assert "satisfied" in verdict.text.lower()
    wait.until(ec.text_to_be_present_in_element((By.ID, "status"), "Done"))
    parts = browser.find_elements(By.CSS_SELECTOR, "#parts tbody tr")
    assert len(parts) >= 1 and SENTENCE.split(" should")[0] in parts[0].text
    metrics = browser.find_element(By.ID, "metrics").text
    assert "fail" in metrics and "unguided" in metrics
    assert "make_loss" in browser.find_element(By.ID, "code").text
    links = [a.text for a in browser.find_elements(By.CSS_SELECTOR, "#downloads a")]
    assert {"metrics.json", "rollout.parquet"} <= set(links)
    # play it again from the start and watch the time go on (once the first playing has ended: the
    # button pauses a playing animation, and a fast unguided run can be done before the animation is)
    wait.until(lambda d: d.find_element(By.ID, "play").text == "Play")
    browser.find_element(By.ID, "play").click()
    start = float(browser.find_element(By.ID, "time-label").text.split()[2])
    wait.until(lambda d: float(d.find_element(By.ID, "time-label").text.split()[2]) > start + 0.5)
    browser.find_element(By.ID, "play").click()  # pause
    collisions = [td for td in browser.find_elements(By.CSS_SELECTOR, "#events td") if " s with " in td.text]
    if collisions:  # a click on an event's time shows that moment
        collisions[0].click()
        clock = float(collisions[0].text.split()[0])
        assert abs(float(browser.find_element(By.ID, "time-label").text.split()[2]) - clock) < 0.051
    assert _hover(browser, 2).startswith("vehicle 2 · vehicle · ")
    _screenshot(browser, tmp_path, "serve-run.png")
