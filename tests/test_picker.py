"""`rigsfm pick` in a real headless Chromium: click pairs, epipolar line, flagging, autosave, undo, reload."""

import http.client

import numpy as np
import pytest
from support import browser_page
from test_manual_matches import A, B, synthetic_correspondences

from rigsfm.pick import start_picker
from rigsfm.run.matching.manual_matches import read_manual_matches
from rigsfm.synth.clicks import farthest_points
from rigsfm.synth.scene import SceneOptions

pytestmark = pytest.mark.slow  # end-to-end runs on rendered images (`-m 'not slow'` skips them)



@pytest.fixture(scope="module")
def dataset(rendered):
    return rendered(SceneOptions(num_rigs=2, arc_deg=60.0, image_scale=0.5, seed=4))


@pytest.fixture()
def page(dataset, tmp_path):
    server = start_picker(dataset.images / A, dataset.images / B, tmp_path / "matches.csv", dataset.rigs)
    with browser_page(server, "window.picker.ready") as page:
        yield page, server, tmp_path / "matches.csv"
    server.close()


def click(page, side, xy):
    x, y = page.evaluate(f"window.picker.toScreen('{side}', {xy[0]}, {xy[1]})")
    page.mouse.click(round(x), round(y))
    return page.evaluate(f"window.picker.toImage('{side}', {round(x)}, {round(y)})")


def distance_to_polyline(points, xy):
    p = np.asarray(points, dtype=float)
    a, b = p[:-1], p[1:]
    t = np.clip(np.einsum("ij,ij->i", xy - a, b - a) / np.einsum("ij,ij->i", b - a, b - a), 0, 1)
    return float(np.min(np.linalg.norm(a + t[:, None] * (b - a) - xy, axis=1)))


def spread_correspondences(dataset, n, seed):
    """``n`` exact correspondences spread over image A (farthest-point sampling), like a careful user's."""
    rows, _ = synthetic_correspondences(dataset, n=80, noise_px=0.0, outlier_fraction=0.0, seed=seed)
    chosen = farthest_points(np.array([r.xy_a for r in rows]), n, np.random.default_rng(seed))
    return [rows[i] for i in chosen]


def settle(page, n):
    """Wait for ``n`` pairs in the table and for every save to be answered by the server."""
    page.wait_for_function(f"document.querySelectorAll('#pairs tbody tr').length === {n}")
    page.evaluate("window.picker.saved()")


def table_rows(page):
    return page.locator("#pairs tbody tr")


def test_pick_pairs_epipolar_line_flag_save_undo_reload(page, dataset):
    page, _, csv = page
    rows = spread_correspondences(dataset, 10, seed=1)
    clicked = []
    for row in rows[:8]:
        clicked.append(click(page, "a", row.xy_a) + click(page, "b", row.xy_b))
        assert page.locator("#epipolar-b").count() == 0  # no model before eight pairs
    settle(page, 8)
    assert "epipolar lines from 8 pairs (calibrated E)" in page.locator("#status").inner_text()

    # The ninth point: its epipolar curve appears in the other image and passes its true partner.
    clicked.append(click(page, "a", rows[8].xy_a))
    page.wait_for_selector("#epipolar-b")
    points = [[float(v) for v in p.split(",")] for p in page.get_attribute("#epipolar-b", "points").split()]
    assert len(points) > 10 and distance_to_polyline(points, np.array(rows[8].xy_b)) < 3.0
    clicked[-1] += click(page, "b", rows[8].xy_b)
    settle(page, 9)
    assert page.locator("#epipolar-b").count() == 0 and table_rows(page).locator(".flagged").count() == 0

    # Zoomed in, a click still lands where it should; a wrong partner (30 px off its line) is flagged.
    wrong_b = (rows[9].xy_b[0], rows[9].xy_b[1] + 30.0)
    page.mouse.move(*page.evaluate(f"window.picker.toScreen('b', {wrong_b[0]}, {wrong_b[1]})"))
    page.mouse.wheel(0, -600)
    page.wait_for_function("window.picker.views.b.s > 1.5")
    clicked.append(click(page, "a", rows[9].xy_a) + click(page, "b", wrong_b))
    page.wait_for_function("document.querySelectorAll('#pairs tbody tr.flagged').length === 1")
    assert table_rows(page).nth(9).get_attribute("class").startswith("flagged")
    assert np.allclose(clicked[-1][2:], wrong_b, atol=0.5 / page.evaluate("window.picker.views.b.s") + 1e-6)

    # Autosaved: the CSV holds exactly the clicked coordinates (COLMAP pixels).
    saved = read_manual_matches(csv)
    assert [(r.image_a, r.image_b) for r in saved] == [(A, B)] * 10
    assert np.allclose([[*r.xy_a, *r.xy_b] for r in saved], clicked, atol=1e-3)

    page.keyboard.press("Control+z")
    settle(page, 9)
    assert len(read_manual_matches(csv)) == 9
    page.reload()
    page.evaluate("window.picker.ready")
    assert table_rows(page).count() == 9 and table_rows(page).locator(".flagged").count() == 0


def test_pairs_clicked_while_a_save_is_slow_are_all_kept(page, dataset):
    """The first save is held back until two more pairs are clicked: no pair may be lost or reordered."""
    page, server, csv = page
    held = []

    def hold_first_save(route):
        if route.request.method == "PUT" and not held:
            held.append(route)
        else:
            route.continue_()

    page.route("**/api/pairs", hold_first_save)
    rows = spread_correspondences(dataset, 3, seed=3)
    clicked = [click(page, "a", row.xy_a) + click(page, "b", row.xy_b) for row in rows]
    assert len(held) == 1 and len(server.session.pairs) == 0
    held[0].continue_()
    page.evaluate("window.picker.saved()")
    assert table_rows(page).count() == 3 and "NOT SAVED" not in page.locator("#status").inner_text()
    saved = read_manual_matches(csv)
    assert np.allclose([[*r.xy_a, *r.xy_b] for r in saved], clicked, atol=1e-3)
    assert len(server.session.pairs) == 3


def test_state_survives_a_new_server_and_foreign_hosts_are_refused(page, dataset):
    page, _, csv = page
    rows = spread_correspondences(dataset, 3, seed=2)
    for row in rows:
        click(page, "a", row.xy_a)
        click(page, "b", row.xy_b)
    settle(page, 3)
    # A new picker on the same CSV (e.g. after a crash) starts from what was saved.
    again = start_picker(dataset.images / A, dataset.images / B, csv)
    try:
        assert len(again.session.pairs) == 3
        host, port = again.httpd.server_address
        connection = http.client.HTTPConnection(host, port, timeout=5)
        connection.request("GET", "/api/state", headers={"Host": "evil.example:80"})
        assert connection.getresponse().status == 403
    finally:
        again.close()


def test_a_tab_left_open_adds_its_pair_to_the_newer_ones(page, dataset):
    """Two tabs on one picker: the second, opened before the first saved anything, clicks one pair; the CSV keeps
    the first tab's three and adds it, and the second tab then shows all four."""
    page, server, csv = page
    other = page.context.browser.new_page(viewport={"width": 1800, "height": 1100})
    other.goto(server.url)
    other.evaluate("window.picker.ready")
    rows = spread_correspondences(dataset, 4, seed=5)
    for row in rows[:3]:
        click(page, "a", row.xy_a)
        click(page, "b", row.xy_b)
    settle(page, 3)
    click(other, "a", rows[3].xy_a)
    click(other, "b", rows[3].xy_b)
    settle(other, 4)
    saved = read_manual_matches(csv)
    assert np.allclose([r.xy_a for r in saved], [r.xy_a for r in rows], atol=0.5)
    assert "NOT SAVED" not in other.locator("#status").inner_text()
