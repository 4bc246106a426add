"""Lab study, outside the installed package.
Question: How soon does the web page show its first 3D view?
Answer: docs/results.md; the measurements: docs/notebook/benchmarks.md,
"A service and a web page".

The web page's first view, measured in headless Chromium: `rllock serve` started afresh, the page
opened the moment /api/health answers, then opened again `--loads` times; for each load, the
milliseconds from the request for the page to its first 3D view of a shape (the page's own
`window.firstViewMs`, with the shape list filled and the preview drawn).

    .venv/bin/python lab/first_view.py [--loads 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

from rllock.orchestration.bench.serve import ServerProcess


def first_view_ms(driver: webdriver.Chrome, url: str) -> float:
    driver.get(url)
    WebDriverWait(driver, 30).until(
        lambda d: d.find_element(By.TAG_NAME, "body").get_attribute("data-phase") == "ready"
    )
    return float(driver.execute_script("return window.firstViewMs"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loads", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="rllock-first-view-") as folder:
        options = webdriver.ChromeOptions()
        options.binary_location = "/usr/bin/chromium"
        for flag in (
            "--headless=new",
            "--no-sandbox",
            "--enable-unsafe-swiftshader",
            f"--user-data-dir={folder}/p",
        ):
            options.add_argument(flag)
        driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
        server = ServerProcess(Path(folder) / "data")
        try:
            up = server.start()
            began = time.monotonic()
            first = first_view_ms(driver, server.url + "/")
            after_up = (time.monotonic() - began) * 1000
            again = [first_view_ms(driver, server.url + "/") for _ in range(args.loads)]
        finally:
            server.stop()
            driver.quit()
    print(
        json.dumps(
            {
                "server_up_s": round(up, 2),
                "first_load_ms": round(first, 1),
                "first_load_wall_ms_after_health": round(after_up, 1),
                "later_loads_ms": [round(v, 1) for v in again],
                "later_median_ms": round(statistics.median(again), 1),
            }
        )
    )


if __name__ == "__main__":
    main()
