"""The service's page in a real headless Chromium (selenium): a street image is uploaded through the page's file
input and the answer is read back from the DOM: the top-k tiles, the confidence, the heading. A file name that is
HTML stays text; bad uploads show the service's error. Skips only where no Chromium / chromedriver is installed."""

from __future__ import annotations

import shutil
import time

import cv2
import numpy as np
import pytest
from geoloc.apps.serve import create_app
from helpers.calibrated import KNOWN, calibrated_copy
from test_localize import gallery  # noqa: F401  (a fixture: a 1-epoch TINY checkpoint and its saved gallery)
from test_serve import serving

from conftest import REALDATA

pytestmark = pytest.mark.slow
HOSTILE = "<img src=x onerror=alert(1)>.jpg"


def browser_paths() -> tuple[str, str]:
    browser = next(filter(None, map(shutil.which, ("chromium", "chromium-browser", "google-chrome"))), None)
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.skip("no Chromium and chromedriver on this machine (Debian: apt-get install chromium "
                    "chromium-driver; .ci/run installs them): the page's browser test needs a real browser")
    return browser, driver


@pytest.fixture(scope="module")
def browser():
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e .[dev])")
    from selenium.webdriver.chrome.service import Service

    binary, driver_path = browser_paths()
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                 "--window-size=1280,1100"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def page(gallery, tmp_path_factory):  # noqa: F811
    from geoloc.apps.localize import Localizer

    root, ckpt, folder = gallery
    calibrated = calibrated_copy(folder, tmp_path_factory.mktemp("page") / "gallery")
    localizer = Localizer.load(ckpt, calibrated, device="cpu")
    with serving(create_app(localizer)) as url:
        yield root, localizer, url


def ask(driver, url, image, **fields) -> None:
    """Open the page, choose `image` in its file input, fill the fields, press Localize, wait for the answer."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get(url + "/")
    driver.find_element(By.ID, "image").send_keys(str(image))
    for key, value in fields.items():
        box = driver.find_element(By.ID, key)
        box.clear()
        box.send_keys(str(value))
    driver.find_element(By.ID, "submit").click()
    WebDriverWait(driver, 60).until(lambda d: d.find_element(By.ID, "error").text
                                    or d.find_element(By.ID, "status").text.startswith("answered"))


def text(driver, element_id: str) -> str:
    return driver.find_element("id", element_id).get_attribute("textContent")


def shown_hits(driver) -> list[str]:
    return [li.get_attribute("textContent") for li in driver.find_elements("css selector", "#hits li")]


def test_the_page_uploads_an_image_and_shows_the_answer_with_a_hostile_file_name_as_text(page, browser, tmp_path):
    from selenium.common.exceptions import NoAlertPresentException

    root, localizer, url = page
    pano = max((root / "streetview" / "panos").glob("*.jpg"))
    hostile = tmp_path / HOSTILE
    shutil.copy(pano, hostile)
    ask(browser, url, hostile, heading=0, topk=3)
    assert text(browser, "error") == ""
    assert text(browser, "filename") == HOSTILE  # shown as text, never parsed
    assert browser.execute_script("return document.querySelectorAll('img[src=\"x\"], [onerror]').length") == 0
    with pytest.raises(NoAlertPresentException):
        browser.switch_to.alert.text
    from geoloc.apps.localize import read_street

    direct = localizer.localize(read_street(hostile), topk=3, heading=0.0, name=HOSTILE)
    hits = shown_hits(browser)
    assert len(hits) == 3
    # the tiles are on the page, not inside another element that shares an id (the list once had the form's
    # "topk" id, so its items went into the number field, present but never drawn)
    assert browser.execute_script("const ids = [...document.querySelectorAll('[id]')].map(e => e.id);"
                                  "return ids.length === new Set(ids).size")
    assert all(li.is_displayed() and li.size["height"] > 0
               for li in browser.find_elements("css selector", "#hits li"))
    for hit, row in zip(hits, direct.topk):
        assert f"#{row['rank']} score {row['score']:.3f}" in hit and row["path"] in hit
    assert text(browser, "confidence").startswith(f"{100 * direct.confidence:.1f}%")
    assert direct.confidence == pytest.approx(float(KNOWN.probability(
        [[direct.topk[0]["score"], direct.topk[0]["score"] - direct.topk[1]["score"]]])[0]))
    assert text(browser, "status") == f"answered {HOSTILE}"
    # the tiles come from the service's /tiles route and load
    time.sleep(0.5)
    loaded = browser.execute_script("return [...document.querySelectorAll('#hits img')].map(i => i.naturalWidth)")
    assert len(loaded) == 3 and all(width > 0 for width in loaded)
    browser.set_window_size(1280, 1400)  # the whole answer, top-k tiles included
    browser.save_screenshot(str(tmp_path / "page.png"))  # the page as the test left it (pytest keeps the folder)
    browser.set_window_size(1280, 1100)


def test_the_page_shows_a_real_panorama_answered_with_a_searched_heading_as_uncalibrated(page, browser):
    pano = REALDATA / "cvusa_mini" / "streetview" / "panos" / "0000001.jpg"
    if not pano.is_file():
        pytest.skip(f"the real CVUSA sample {pano} is not on this machine (../shared/realdata)")
    ask(browser, page[2], pano, heading="search")  # a north-aligned checkpoint searches only when asked
    assert text(browser, "error") == ""
    assert len(shown_hits(browser)) == 5
    assert text(browser, "confidence").startswith("uncalibrated")
    assert "(search)" in text(browser, "heading-out")


def test_the_page_shows_why_an_upload_or_a_setting_is_refused(page, browser, tmp_path):
    url = page[2]
    notes = tmp_path / "notes.txt"
    notes.write_text("not an image")
    ask(browser, url, notes)
    assert text(browser, "error") == "notes.txt is not a JPEG or PNG image (it is text/plain): choose a street image"
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(cv2.imencode(".jpg", np.full((32, 128, 3), 90, np.uint8))[1].tobytes()[:300])
    ask(browser, url, cut)
    assert text(browser, "error").startswith("415: the upload 'cut.jpg' is not an image")
    pano = max((page[0] / "streetview" / "panos").glob("*.jpg"))
    ask(browser, url, pano, abstain=2)
    assert text(browser, "error").startswith("422: form field abstain=") and "[0, 1]" in text(browser, "error")
    ask(browser, url, pano, heading_prior=20)
    assert "given without heading" in text(browser, "error")
