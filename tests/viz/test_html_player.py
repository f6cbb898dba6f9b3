"""The HTML player of ``mtex view`` (:func:`mtex_jax.viz.write_html`), tested in a real headless
Chromium through Selenium: the page loads without errors, draws the figures above the floor,
plays, pauses, seeks from the texton timeline, shows texton statistics and the vocabulary; and
the ``mtex view`` command.

The browser is the system's Chromium and chromedriver (Debian: ``apt-get install chromium
chromium-driver``; ``.ci/run`` installs them). Without them these tests fail in CI (``CI`` set)
and are skipped, with the install command, elsewhere.
Screenshots are kept in ``tests/artifacts/view/`` (ignored by git).
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import edit_setup
import mtex_jax as mj
from mtex_jax.cli import main
from mtex_jax.viz import write_html

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts" / "view"
FPS = edit_setup.FPS


# ---------------------------------------------------------------------------------------------
# fixtures: the browser, a texture with a synthesis, and the page
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser():
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.fail('the HTML player tests need selenium: pip install -e ".[test]"')
    chrome = next(
        (shutil.which(n) for n in ("chromium", "chromium-browser") if shutil.which(n)), None
    )
    driver_path = shutil.which("chromedriver")
    if chrome is None or driver_path is None:
        why = (
            "the HTML player tests need a system Chromium and chromedriver on PATH (found "
            f"chromium={chrome}, chromedriver={driver_path}); on Debian: apt-get install "
            "chromium chromium-driver (.ci/run does this)"
        )
        # CI installs the browser, so there a missing one is a failure; on a fresh machine
        # (the README's test command) the tests say what to install
        if os.environ.get("CI"):
            pytest.fail(why)
        pytest.skip(why)
    opts = webdriver.ChromeOptions()
    opts.binary_location = chrome
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--disable-gpu",
        "--window-size=1280,1000",
        "--force-device-scale-factor=1",
    ):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(driver_path), options=opts)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def case():
    """A small texture learned on the DeepMimic clips at 30 Hz, a synthesis from it and a real
    clip (the texture and synthesis of the edit tests)."""
    tex = edit_setup.texture()
    syn = edit_setup.synthesis(tex)
    clips = [mj.load_example(n).resample(FPS) for n in mj.io.example_names()]
    real = mj.load_example("walk")
    return tex, syn, clips, real


@pytest.fixture(scope="module")
def page(case, tmp_path_factory):
    tex, syn, clips, real = case
    path = tmp_path_factory.mktemp("view") / "page.html"
    write_html(path, [syn, real], labels=["new dance", "real: walk"], texture=tex, gallery=clips)
    return path


def _open(browser, path: Path) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    browser.get_log("browser")  # drop messages of earlier pages
    browser.get(path.as_uri())
    WebDriverWait(browser, 20).until(lambda d: d.execute_script("return !!window.mtex"))


def _frame(browser) -> int:
    text = browser.find_element("id", "frame-counter").text
    m = re.match(r"frame (\d+) / (\d+)", text)
    assert m, text
    return int(m.group(1))


def _settle(browser) -> None:
    """Wait for two animation frames, so that the page has drawn its current state."""
    browser.execute_async_script(
        "const done = arguments[0];"
        "requestAnimationFrame(() => requestAnimationFrame(() => done(true)));"
    )


_COUNT_PIXELS = """
const c = arguments[0];
const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
let ink = 0, bones = 0;
for (let i = 0; i < d.length; i += 4) {
  const r = d[i], g = d[i + 1], b = d[i + 2];
  if (r < 240 || g < 240 || b < 240) ink++;
  if ((r > 150 && g < 90 && b < 90) || (b > 150 && r < 90 && g < 140)) bones++;
}
return [ink, bones, c.width * c.height];
"""


def _errors(browser) -> list[str]:
    logs = [e["message"] for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    return logs + list(browser.execute_script("return window.mtex.errors"))


# ---------------------------------------------------------------------------------------------
# the file
# ---------------------------------------------------------------------------------------------
def _data(path: Path) -> dict:
    text = path.read_text(encoding="utf-8")
    m = re.search(r'<script type="application/json" id="mtex-data">(.*?)</script>', text, re.S)
    assert m
    return json.loads(m.group(1))


def test_page_is_one_small_file_that_needs_no_network(page, case):
    text = page.read_text(encoding="utf-8")
    assert not re.search(r"\b(src|href)\s*=", text), "the page must not load other files"
    assert "http://" not in text and "https://" not in text
    assert page.stat().st_size < 1_000_000
    data = _data(page)
    tex, syn, _, real = case
    assert [m["label"] for m in data["motions"]] == ["new dance", "real: walk"]
    n_real = int(np.floor((real.n_frames - 1) * FPS / real.fps + 1e-9)) + 1
    assert data["fps"] == FPS and data["n_frames"] == max(syn.n_frames, n_real)
    assert len(data["textons"]["count"]) == tex.n_textons


def test_positions_are_stored_to_a_millimetre(page, case):
    """The stored points, decoded as the player does, keep the figure's shape: every point's
    distance to the root equals forward kinematics' to within a millimetre."""
    _, syn, _, _ = case
    fig = _data(page)["motions"][0]
    q = np.frombuffer(base64.b64decode(fig["pos"]), dtype="<i2").reshape(fig["n"], fig["P"], 3)
    p = np.asarray(fig["origin"]) + q * fig["unit"]
    fk = np.asarray(mj.forward_kinematics(syn.motion, end_sites=True))[:, fig["points"]]
    assert fig["points"][0] == 0  # the root comes first
    got = np.linalg.norm(p - p[:, :1], axis=-1)
    want = np.linalg.norm(fk - fk[:, :1], axis=-1)
    assert np.abs(got - want).max() < 1.5e-3
    assert p[..., 2].min() == pytest.approx(0.0, abs=1e-3)  # standing on the floor


def test_a_page_of_two_salsa_clips_is_small(tmp_path):
    """Under 8 kB per second of a CMU salsa figure at 30 Hz (about 6.5 kB measured) and 30 kB
    for the player: the demo's page (a 20 s dance, a held-out clip of up to 19 s, a gallery of
    at most 60 textons of at most 3 s) stays below its budget of 3 MB."""
    clips = [mj.io.load_salsa(n) for n in ("60_13", "60_15")]
    page = write_html(tmp_path / "salsa.html", clips)
    seconds = sum(m.duration for m in clips)
    assert page.stat().st_size < 30_000 + 8_000 * seconds
    assert 30_000 + 8_000 * (20 + 19 + 60 * 3) < 2e6


def test_write_html_refuses_bad_input(tmp_path, case):
    tex, _, _, real = case
    out = tmp_path / "p.html"
    with pytest.raises(TypeError, match="Motion or a Synthesis"):
        write_html(out, [real, np.zeros((3, 4))])
    with pytest.raises(ValueError, match="labels must be 2 strings"):
        write_html(out, [real, real], labels=["one"])
    with pytest.raises(ValueError, match="integer rows"):
        write_html(out, real, timelines=[np.zeros((2, 2), dtype=int)])
    with pytest.raises(ValueError, match="ends after"):
        write_html(out, real, timelines=[np.array([[0, real.n_frames + 1, 0]])])
    with pytest.raises(ValueError, match="beyond the texture"):
        write_html(out, real, timelines=[np.array([[0, 2, tex.n_textons]])], texture=tex)
    with pytest.raises(ValueError, match="fps"):
        write_html(out, real, fps=0)
    with pytest.raises(ValueError, match="does not exist"):
        write_html(tmp_path / "nowhere" / "p.html", real)
    assert not out.exists()


# ---------------------------------------------------------------------------------------------
# the page in a browser
# ---------------------------------------------------------------------------------------------
def test_page_loads_without_errors_and_draws_the_figures(browser, page):
    _open(browser, page)
    _settle(browser)
    canvas = browser.find_element("id", "view")
    ink, bones, total = browser.execute_script(_COUNT_PIXELS, canvas)
    assert _errors(browser) == []
    assert ink > 0.05 * total, "the floor and figures cover part of the canvas"
    assert bones > 300, "the red and blue limbs are drawn"


def test_frame_counter_advances_while_playing_and_stops_when_paused(browser, page):
    _open(browser, page)
    browser.execute_script("window.mtex.seek(0)")
    _settle(browser)
    t0, f0 = time.perf_counter(), _frame(browser)
    time.sleep(0.8)
    f1, elapsed = _frame(browser), time.perf_counter() - t0
    assert 0.4 * elapsed * FPS <= f1 - f0 <= elapsed * FPS + 3
    browser.find_element("id", "play").click()  # pause
    assert browser.execute_script("return window.mtex.playing()") is False
    f2 = _frame(browser)
    time.sleep(0.4)
    assert _frame(browser) == f2
    # a quarter of the speed: at most a quarter of the frames
    browser.execute_script(
        "const s = document.getElementById('speed'); s.value = '0.25';"
        "s.dispatchEvent(new Event('change')); window.mtex.seek(0);"
    )
    browser.find_element("id", "play").click()
    t0 = time.perf_counter()
    time.sleep(0.8)
    f3, elapsed = _frame(browser), time.perf_counter() - t0
    assert 0 < f3 <= 0.25 * elapsed * FPS + 3


def test_timeline_click_seeks_to_the_first_frame_of_the_texton(browser, page, case):
    _, syn, _, _ = case
    _open(browser, page)
    browser.execute_script("window.mtex.pause()")
    bars = browser.find_elements("css selector", ".seg")
    path, starts = np.asarray(syn.path), np.asarray(syn.starts)
    assert [int(b.get_attribute("data-texton")) for b in bars] == path.tolist()
    for bar, start in reversed(list(zip(bars, starts, strict=True))):
        bar.click()
        _settle(browser)
        assert _frame(browser) == start
        assert browser.find_element("id", "slider").get_attribute("value") == str(start)


def test_hovering_a_segment_shows_the_texton_statistics(browser, page, case):
    from selenium.webdriver.common.action_chains import ActionChains

    tex, syn, _, _ = case
    _open(browser, page)
    bar = browser.find_elements("css selector", ".seg")[1]
    ActionChains(browser).move_to_element(bar).perform()
    tip = browser.find_element("id", "tooltip")
    assert tip.is_displayed()
    lab = int(np.asarray(syn.path)[1])
    count, mean = tex.length_stats()[lab, :2]
    best = int(np.argmax(np.asarray(tex.M)[lab]))
    assert f"texton {lab}" in tip.text
    assert f"training segments: {int(count)} · mean {mean / FPS:.2f} s" in tip.text
    assert re.search(rf"top successors: {best} \(\d+ %\)", tip.text), tip.text


def test_figures_stand_upright_above_the_floor_and_in_view(browser, page):
    _open(browser, page)
    browser.execute_script("window.mtex.pause()")
    n = browser.execute_script("return window.mtex.nFrames")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for k, f in enumerate((0, n // 3, 2 * n // 3, n - 1)):
        browser.execute_script(f"window.mtex.seek({f})")
        _settle(browser)
        for fig in browser.execute_script("return window.mtex.check()"):
            assert fig["footHeight"] >= -1e-3, fig
            assert fig["headY"] < fig["footY"] <= fig["floorY"] + 0.5, fig  # y grows downwards
            assert 0 <= fig["headY"] and fig["floorY"] <= fig["height"], fig
            assert 0 <= fig["footX"] <= fig["width"], fig
        shot = ARTIFACTS / f"player_{k}.png"
        browser.save_screenshot(str(shot))
    with Image.open(shot) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    assert ((r > 150) & (g < 90) & (b < 90)).sum() > 100  # right limbs (red)
    assert ((b > 150) & (r < 90) & (g < 140)).sum() > 100  # left limbs (blue)


def _pixels(browser) -> np.ndarray:
    """The page's screenshot as an RGB array."""
    import io

    with Image.open(io.BytesIO(browser.get_screenshot_as_png())) as im:
        return np.asarray(im.convert("RGB")).astype(int)


def test_orbit_and_zoom_move_the_camera(browser, page):
    from selenium.webdriver.common.action_chains import ActionChains

    _open(browser, page)
    browser.execute_script("window.mtex.pause()")
    _settle(browser)
    before = browser.execute_script("return window.mtex.check()")[0]
    canvas = browser.find_element("id", "view")
    shot0 = _pixels(browser)
    ActionChains(browser).click_and_hold(canvas).move_by_offset(150, 0).release().perform()
    _settle(browser)
    # the paused scene seen from another side: the floor grid and the figure move on screen
    # (a figure standing on the orbit's axis barely moves sideways, so compare the pictures)
    changed = np.mean(np.any(_pixels(browser) != shot0, axis=-1))
    assert changed > 0.01, changed
    ActionChains(browser).double_click(canvas).perform()  # back to the starting camera
    _settle(browser)
    home = browser.execute_script("return window.mtex.check()")[0]
    assert home["footX"] == pytest.approx(before["footX"], abs=0.5)
    browser.execute_script(
        "arguments[0].dispatchEvent(new WheelEvent('wheel', {deltaY: -400, cancelable: true}))",
        canvas,
    )
    _settle(browser)
    near = browser.execute_script("return window.mtex.check()")[0]
    assert near["footY"] - near["headY"] > 1.2 * (home["footY"] - home["headY"])
    assert _errors(browser) == []


def test_gallery_shows_every_texton_as_a_small_player(browser, page, case):
    tex, _, _, _ = case
    _open(browser, page)
    cards = browser.find_elements("css selector", ".card")
    counts = tex.length_stats()[:, 0]
    assert len(cards) == int((counts > 0).sum())
    first = int(np.flatnonzero(counts > 0)[0])
    assert f"texton {first}" in cards[0].text and "training clip" in cards[0].text
    browser.execute_script("arguments[0].scrollIntoView()", cards[0])
    _settle(browser)
    _settle(browser)
    canvas = cards[0].find_element("css selector", "canvas")
    ink, bones, _ = browser.execute_script(_COUNT_PIXELS, canvas)
    assert ink > 500 and bones > 20
    browser.save_screenshot(str(ARTIFACTS / "gallery.png"))
    # a click on a card picks its texton out in the timeline
    cards[0].click()
    bars = browser.find_elements("css selector", ".seg")
    for bar in bars:
        dim = "dim" in bar.get_attribute("class").split()
        assert dim == (int(bar.get_attribute("data-texton")) != first)


# ---------------------------------------------------------------------------------------------
# mtex view
# ---------------------------------------------------------------------------------------------
def test_mtex_view_of_a_texture_model_and_a_bvh_file(browser, tmp_path, case, capsys):
    tex, _, _, real = case
    model, bvh, out = tmp_path / "model.npz", tmp_path / "walk.bvh", tmp_path / "view.html"
    tex.save(model)
    mj.write_bvh(bvh, real)
    assert main(["view", str(model), str(bvh), "-o", str(out), "--seconds", "2"]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    data = _data(out)
    assert [m["label"] for m in data["motions"]] == [
        "model.npz: synthesis (seed 0)",
        "walk.bvh",
    ]
    assert data["motions"][0]["timeline"] and data["motions"][1]["timeline"] is None
    _open(browser, out)
    _settle(browser)
    assert _errors(browser) == []
    cards = browser.find_elements("css selector", ".card")
    assert len(cards) == int((tex.length_stats()[:, 0] > 0).sum())
    assert "sample (zero noise)" in cards[0].text
    browser.save_screenshot(str(ARTIFACTS / "mtex_view.png"))


def test_mtex_view_reports_bad_input_in_one_line(tmp_path, capsys, case):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a model")
    bvh = tmp_path / "walk.html"  # a BVH file with the name of a page
    mj.write_bvh(bvh, case[3])
    before = bvh.read_bytes()
    out = str(tmp_path / "v.html")
    cases = [
        (["view", "example:walk", "-o", str(tmp_path / "v.gif")], "must end in .html"),
        (["view", str(tmp_path / "missing.bvh"), "-o", out], "missing.bvh"),
        (["view", str(junk), "-o", out], "junk.npz"),
        (["view", str(junk), str(junk), "-o", out], "at most one texture model"),
        (["view", "example:walk", "--labels", "a,b", "-o", out], "--labels needs 1"),
        (["view", "example:walk", "--fps", "0", "-o", out], "--fps"),
        (["view", "example:walk", "--fps", "nan", "-o", out], "--fps"),
        (["view", "example:walk", "--seed", "-1", "-o", out], "--seed"),
        (["view", "example:walk", "-o", str(tmp_path / "no" / "v.html")], "does not exist"),
        (["view", str(bvh), "-o", str(bvh)], "is also an input"),
        (["view", "example:walk", "-o", str(bvh)], "needs --force"),
    ]
    for args, words in cases:
        assert main(args) == 2, args
        err = capsys.readouterr().err
        assert err.startswith("mtex: error: ") and err.count("\n") == 1, err
        assert words in err, err
    assert [p.name for p in tmp_path.glob("*.html")] == ["walk.html"]
    assert bvh.read_bytes() == before


def test_timeline_follows_the_player_frame_rate(tmp_path, case):
    """At 15 Hz the player shows every second frame of the 30 Hz synthesis; its segments start
    at half the frame and still tile the clip."""
    _, syn, _, _ = case
    data = _data(write_html(tmp_path / "p.html", syn, fps=15.0, contacts=False))
    fig = data["motions"][0]
    assert data["fps"] == 15.0 and fig["n"] == (syn.n_frames - 1) // 2 + 1
    rows = np.asarray(fig["timeline"])
    assert rows[:, 0].tolist() == np.rint(np.asarray(syn.starts) / 2).astype(int).tolist()
    assert rows[:, 2].tolist() == np.asarray(syn.path).tolist()
    assert (rows[1:, 0] == rows[:-1, 0] + rows[:-1, 1]).all() and rows[:, 1].sum() == fig["n"]
    assert fig["contact"] == "" and data["gallery"] == []
