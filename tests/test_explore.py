"""`rigsfm explore` in a real headless Chromium on the rendered 3-rig run: a click's band in the other views drawn
where the ground truth says, triangulation against the truth, saving and resuming, foreign rows, --check, refusals.

``RIGSFM_SCREENSHOT_DIR=docs`` writes the page's screenshot there as a JPEG (the README's docs/explore.jpg), made on
the same network with a textured centre (``python -m rigsfm.synth S --num-rigs 3 --arc-deg 120 --image-scale 0.5
--seed 1 --textured-centre``, then ``rigsfm run``) so the narrow images show something; without it the tests use the
session's 3-rig run."""

import http.client
import json
import os
from pathlib import Path
from urllib.parse import urlencode

import cv2
import numpy as np
import pycolmap
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support import browser_page
from typer.testing import CliRunner

from rigsfm.cli import app
from rigsfm.core.errors import InputError
from rigsfm.core.geometry import project_world
from rigsfm.explore import ExploreOptions, check_labels, start_explorer
from rigsfm.explore.geometry import _moved, distance_to_polyline, ray_at_heights, triangulate
from rigsfm.explore.labels import Label, person_problem, read_labels, save_labels
from rigsfm.explore.session import ExploreResult, parse_heights

slow = pytest.mark.slow  # end-to-end on a rendered run (`-m 'not slow'` skips it)


@pytest.fixture(scope="module")
def run(request, tmp_path_factory):
    if not os.environ.get("RIGSFM_SCREENSHOT_DIR"):
        dataset, out, _ = request.getfixturevalue("three_rig_run")
        return dataset, out
    from rigsfm.synth.dataset import render_dataset
    from rigsfm.synth.scene import SceneOptions

    root = tmp_path_factory.mktemp("textured")
    dataset = render_dataset(root / "scene", SceneOptions(num_rigs=3, arc_deg=120.0, image_scale=0.5, seed=1,
                                                          textured_centre=True))
    result = CliRunner().invoke(app, ["run", str(dataset.images), "--rigs", str(dataset.rigs), "--scale",
                                      str(dataset.scale), "--out", str(root / "out")])
    assert result.exit_code == 0, result.output
    return dataset, root / "out"


def true_points(run, count: int, margin_px: float, seed: int = 0) -> tuple[list[str], list[tuple[np.ndarray, dict]]]:
    """``count`` true world points between the floor and 2.2 m seen by two or more narrow views of the run's first
    frame: (xyz in OUT's frame, {view index: true pixel}).

    The points are made in OUT's floor frame, mapped into the truth's frame by the similarity that aligns the true
    camera centres onto the estimated ones, and projected with the *true* cameras."""
    dataset, out = run
    result = ExploreResult(out)
    names = result.frame_names(next(iter(result.frames)))
    gt, est = dataset.load_ground_truth(), result.reconstruction
    common = [im.name for im in est.images.values() if im.has_pose and gt.find_image_with_name(im.name)]
    est_from_gt = pycolmap.estimate_sim3d(np.array([gt.find_image_with_name(n).projection_center() for n in common]),
                                          np.array([est.find_image_with_name(n).projection_center() for n in common]))
    rng = np.random.default_rng(seed)
    found = []
    for trial in range(100 * count):
        view = result.views[names[trial % len(names)]]
        pixel = rng.uniform(0.02, 0.98, 2) * [view.camera.width, view.camera.height]
        xyz = ray_at_heights(view, pixel, rng.uniform(0.0, 2.2, 1))[0]
        if not np.all(np.isfinite(xyz)):
            continue
        seen = {}
        for k, name in enumerate(names):
            image = gt.find_image_with_name(name)
            p, ok = project_world(gt.cameras[image.camera_id], image.cam_from_world(), est_from_gt.inverse() * xyz,
                                  margin_px=margin_px)
            if ok[0]:
                seen[k] = p[0]
        if len(seen) >= 2:
            found.append((xyz, seen))
        if len(found) == count:
            break
    assert len(found) == count
    return names, found


@pytest.fixture(scope="module")
def truth(run):
    """Six true points as (i, xy_i, j, xy_j, xyz): clicked in view i, partner in view j."""
    names, points = true_points(run, 6, margin_px=20)
    return names, [(i, seen[i], j, seen[j], xyz) for xyz, seen in points for i, j in [sorted(seen)[:2]]]


@pytest.fixture()
def page(run, tmp_path):
    _, out = run
    server = start_explorer(out, ExploreOptions(labels=tmp_path / "labels.csv"))
    with browser_page(server, "window.explore.ready") as page:
        yield page, server, tmp_path / "labels.csv"
    server.close()


def click(page, view, xy):
    x, y = page.evaluate(f"window.explore.toScreen({view}, {xy[0]}, {xy[1]})")
    page.mouse.click(round(x), round(y))
    return page.evaluate(f"window.explore.toImage({view}, {round(x)}, {round(y)})")


def polyline(page, selector):
    return np.array([[float(v) for v in p.split(",")] for p in page.get_attribute(selector, "points").split()])


def settle(page, persons):
    page.wait_for_function(f"document.querySelectorAll('#persons tbody tr').length === {persons}")
    page.evaluate("window.explore.saved()")


@slow
def test_band_truth_triangulation_save_resume(page, run, truth, tmp_path):
    page, server, csv = page
    _, out = run
    names, points = truth
    checked = []
    for n, (i, xy_i, j, xy_j, xyz) in enumerate(points[:3]):
        clicked_i = click(page, i, xy_i)
        page.wait_for_selector(f"#band-{j}")
        # The band drawn in view j holds the true partner; the centre curve spans the heights 0-2.2 m.
        centre = polyline(page, f"#centre-{j}")
        half_width = float(page.get_attribute(f"#band-{j}", "stroke-width")) / 2
        distance = distance_to_polyline(centre, xy_j)
        assert len(centre) > 50 and distance <= half_width, (distance, half_width)
        assert half_width == pytest.approx(server.session.result.bands[(names[i], names[j])])
        ticks = page.locator(f"#svg-{j} circle.tick").count()
        assert ticks >= 1
        assert page.locator("#trace").count() == 1  # the ray's trace on the floor map
        if n == 1:  # zoomed in, a click still lands where it should
            page.mouse.move(*page.evaluate(f"window.explore.toScreen({j}, {xy_j[0]}, {xy_j[1]})"))
            fitted = page.evaluate(f"window.explore.views[{j}].s")
            page.mouse.wheel(0, -600)
            page.wait_for_function(f"window.explore.views[{j}].s > {2 * fitted}")
        clicked_j = click(page, j, xy_j)
        scale = page.evaluate(f"window.explore.views[{j}].s")
        assert np.allclose(clicked_j, xy_j, atol=0.5 / scale + 1e-6)
        page.wait_for_selector(f"#ellipse-p{n + 1}")
        page.evaluate("window.explore.saved()")
        person = next(p for p in page.evaluate("window.explore.state.persons") if p["person"] == f"p{n + 1}")
        # Triangulated from the two clicks: the truth lies within the stated uncertainty (3-D, 99.9 %).
        point = np.array(person["point"]["xyz"])
        covariance = np.array(person["point"]["covariance"])
        error = point - xyz
        assert float(error @ np.linalg.solve(covariance, error)) < 16.27, (error, np.sqrt(np.diag(covariance)))
        second = person["clicks"][1]
        assert second["distance_px"] == pytest.approx(distance_to_polyline(centre, clicked_j), abs=0.05)
        assert second["band_units"] == pytest.approx(second["distance_px"] / half_width, abs=1e-3)
        checked.append((clicked_i, clicked_j))
        if n < 2:
            page.click("#next")
    settle(page, 3)  # the last person stays selected: its band shows on the screenshot
    page.screenshot(path=tmp_path / "explore.png")
    assert (tmp_path / "explore.png").stat().st_size > 10_000
    if os.environ.get("RIGSFM_SCREENSHOT_DIR"):
        shot = cv2.imread(str(tmp_path / "explore.png"))
        cv2.imwrite(str(Path(os.environ["RIGSFM_SCREENSHOT_DIR"]) / "explore.jpg"), shot,
                    [cv2.IMWRITE_JPEG_QUALITY, 80])

    # Saved at once, exactly the clicked pixels; read back by a new page and by a new server.
    labels, foreign = read_labels(csv, server.session.result.sizes)
    assert not foreign and [label.person for label in labels] == ["p1", "p1", "p2", "p2", "p3", "p3"]
    assert np.allclose([[label.x, label.y] for label in labels], [xy for pair in checked for xy in pair], atol=1e-3)
    assert csv.read_text().splitlines()[0] == "image,x,y,person"
    page.reload()
    page.evaluate("window.explore.ready")
    assert page.locator("#persons tbody tr").count() == 3
    again = start_explorer(out, ExploreOptions(labels=csv))
    try:
        assert len(again.session.labels) == 6
    finally:
        again.close()
    # A wrong partner (40 px across its band) is measured outside it, and --check counts it.
    i, xy_i, j, xy_j, _ = points[3]
    click(page, i, xy_i)
    page.wait_for_selector(f"#centre-{j}")
    centre = polyline(page, f"#centre-{j}")
    k = int(np.argmin(np.linalg.norm(centre - xy_j, axis=1)))
    tangent = centre[min(k + 1, len(centre) - 1)] - centre[max(k - 1, 0)]
    normal = np.array([-tangent[1], tangent[0]]) / np.linalg.norm(tangent)
    click(page, j, np.asarray(xy_j) + 40 * normal)
    page.wait_for_function("document.querySelectorAll('#persons td.outside').length === 1")
    page.evaluate("window.explore.saved()")
    result = check_labels(out, csv)
    assert (result.pairs, result.inside) == (4, 3)
    cli = CliRunner().invoke(app, ["explore", str(out), "--check", str(csv)], env={"COLUMNS": "200"})
    assert cli.exit_code == 0 and "3 of 4 labelled pairs inside their 95 % band (75.0 %)" in cli.output


@slow
def test_foreign_rows_are_kept_with_a_backup(page, run, truth):
    page, server, csv = page
    names, points = truth
    original = "image,x,y,person\nrig09/narrow/frame0000.png,10,10,p1\nnot,a,label\n"
    csv.write_text(original)
    page.click("#reload")
    page.wait_for_function("document.querySelector('#status').textContent.includes('2 foreign rows')")
    i, xy_i, j, xy_j, _ = points[0]
    click(page, i, xy_i)
    click(page, j, xy_j)
    settle(page, 1)
    lines = csv.read_text().splitlines()
    assert lines[-2:] == ["rig09/narrow/frame0000.png,10,10,p1", "not,a,label"] and len(lines) == 5
    assert csv.with_name("labels.csv.bak").read_text() == original


@slow
def test_refusals(run, tmp_path):
    dataset, out = run
    with pytest.raises(InputError, match="frame 'nope' has no narrow images"):
        start_explorer(out, ExploreOptions(frame="nope"))
    server = start_explorer(out, ExploreOptions(labels=tmp_path / "labels.csv"))
    try:
        host, port = server.httpd.server_address
        with pytest.raises(InputError, match="the port is in use"):
            start_explorer(out, ExploreOptions(labels=tmp_path / "labels.csv"), port=port)
        for path, status in [("/../../etc/passwd", 404), ("/image?view=3", 400), ("/image?view=-1", 400),
                             ("/image?view=0&frame=../../etc/passwd", 400), ("/static/../server.py", 404),
                             ("/explore.js/../../session.py", 404)]:
            connection = http.client.HTTPConnection(host, port, timeout=5)
            connection.request("GET", path)
            assert connection.getresponse().status == status, path
        connection = http.client.HTTPConnection(host, port, timeout=5)
        connection.request("GET", "/api/state?frame=nope")
        answer = connection.getresponse()
        assert answer.status == 400 and "frame 'nope' has no narrow images" in json.loads(answer.read())["error"]
        connection = http.client.HTTPConnection(host, port, timeout=5)
        connection.request("GET", "/api/state", headers={"Host": "evil.example:80"})
        assert connection.getresponse().status == 403
    finally:
        server.close()
    result = CliRunner().invoke(app, ["explore", str(dataset.root), "--frame", "x"], env={"COLUMNS": "200"})
    assert result.exit_code != 0 and "holds no result" in result.output and "Traceback" not in result.output


def test_images_option_that_is_no_folder_is_named_as_the_option(run, tmp_path):
    """--images given and wrong is the option's error, not "the run's IMAGES folder ... (moved?)"."""
    _, out = run
    with pytest.raises(InputError, match=r"^--images .*nowhere is not a folder; give the run's IMAGES folder$"):
        ExploreResult(out, tmp_path / "nowhere")


def test_a_save_that_cannot_be_written_names_the_csv(run, tmp_path):
    """A labels CSV under a file (or on a full disk) is the server's failure, named by the CSV, not a bad request
    naming the temporary file rigsfm writes first."""
    _, out = run
    (tmp_path / "a-file").write_text("")
    csv = tmp_path / "a-file" / "labels.csv"
    server = start_explorer(out, ExploreOptions(labels=csv))
    try:
        host, port = server.httpd.server_address
        names = [v["name"] for v in server.session.state()["views"]]
        body = {"frame": server.session.frame, "labels": [{"image": names[0], "x": 10.0, "y": 10.0, "person": "p1"}]}
        connection = http.client.HTTPConnection(host, port, timeout=30)
        connection.request("PUT", "/api/labels", json.dumps(body).encode(), {"Content-Type": "application/json"})
        answer = connection.getresponse()
        error = json.loads(answer.read())["error"]
        assert answer.status == 500, error
        assert error.startswith(f"cannot save to {csv}: a part of the path is a file, not a folder"), error
        assert ".tmp" not in error and server.session.labels == []
    finally:
        server.close()


def test_labels_on_a_changed_picture_are_set_aside(run, tmp_path, caplog):
    """Clicks belong to the picture they were made on: after a new picture under the same name (a new recording
    re-run with --overwrite), its labels are neither shown nor checked, and the next save keeps them in a backup only;
    the other images' labels are untouched."""
    import shutil

    from rigsfm.explore.session import ExploreSession

    dataset, out = run
    images = tmp_path / "images"
    shutil.copytree(dataset.images, images)
    csv = tmp_path / "labels.csv"
    session = ExploreSession(out, ExploreOptions(labels=csv, images=images))
    names = session.result.frame_names(session.frame)
    session.set_frame_labels(session.frame, [{"image": names[0], "x": 100.0, "y": 120.0, "person": "p1"},
                                             {"image": names[1], "x": 300.0, "y": 200.0, "person": "p1"}])
    assert check_labels(out, csv, ExploreOptions(images=images)).stale == 0
    picture = cv2.imread(str(images / names[0]))
    cv2.imwrite(str(images / names[0]), picture[::-1])  # another picture, the same name and size
    again = ExploreSession(out, ExploreOptions(labels=csv, images=images))
    assert [label.image for label in again.labels] == [names[1]] and "STALE LABELS" in caplog.text
    assert again.state()["stale_labels"] == 1
    checked = check_labels(out, csv, ExploreOptions(images=images))
    assert checked.stale == 1 and checked.pairs == 0
    before = csv.read_text()
    again.set_frame_labels(again.frame, [{"image": names[1], "x": 300.0, "y": 200.0, "person": "p1"},
                                         {"image": names[0], "x": 50.0, "y": 60.0, "person": "p1"}])
    assert csv.with_name("labels.csv.bak").read_text() == before and "100.000" not in csv.read_text()
    assert ExploreSession(out, ExploreOptions(labels=csv, images=images)).stale == []  # the new click is on it


@slow
def test_check_measures_the_bands_coverage_on_true_correspondences(run, tmp_path):
    """Every true correspondence of 300 points (floor to 2.2 m) labelled exactly: the share inside the band is what
    the 95 % band promises (measured 0.98 on the textured-centre run of the same network)."""
    _, out = run
    names, points = true_points(run, 300, margin_px=0, seed=1)
    csv = tmp_path / "truth.csv"
    save_labels(csv, [Label(names[k], *xy, f"p{n + 1}") for n, (_, seen) in enumerate(points)
                      for k, xy in seen.items()], [], backup=False)
    result = check_labels(out, csv, ExploreOptions(click_sigma_px=0.0))  # exact clicks: the bare band
    assert result.pairs >= 300 and result.without_band == 0 and len(result.per_pair) == 3
    assert result.share >= 0.93, result.per_pair
    # A band half as wide holds clearly fewer: the check measures the band, it does not pass anything.
    narrow = [d for d in result.distances if d["distance_px"] <= d["band_px"] / 2]
    assert len(narrow) < 0.9 * result.inside
    # clicks of a person err by click_sigma_px: the CLI's check allows for it, so no fewer are inside
    clicked = check_labels(out, csv)
    assert clicked.inside >= result.inside and all(d["allowed_px"] > d["band_px"] for d in clicked.distances)
    cli = CliRunner().invoke(app, ["explore", str(out), "--check", str(csv)], env={"COLUMNS": "200"})
    assert cli.exit_code == 0
    assert f"{clicked.inside} of {clicked.pairs} labelled pairs inside their 95 % band" in cli.output


@slow
def test_triangulation_covariance_matches_the_spread_of_its_errors(run):
    """Cameras moved by draws of the run's pose sigmas and clicks with 1 px noise: the triangulated points scatter as
    the stated covariance says (mean squared Mahalanobis distance 3 in 3-D, 95 % inside the 95 % ellipsoid)."""
    _, out = run
    result = ExploreResult(out)
    names = result.frame_names(next(iter(result.frames)))
    views = [result.views[n] for n in names]
    assert all(v.centre_sigma_m > 0 and v.rotation_sigma_rad > 0 for v in views)
    rng = np.random.default_rng(0)
    _, points = true_points(run, 3, margin_px=20, seed=2)
    squared = []
    for xyz, seen in points:
        chosen = [views[k] for k in sorted(seen)]
        for _ in range(150):
            moved = [_moved(v, rng.normal(0, v.centre_sigma_m / np.sqrt(3), 3),
                            rng.normal(0, v.rotation_sigma_rad / np.sqrt(3), 3)) for v in chosen]
            clicks = [m.project(xyz)[0][0] + rng.normal(0, 1.0, 2) for m in moved]
            found = triangulate(chosen, clicks, 1.0)
            error = found.xyz - xyz
            squared.append(float(error @ np.linalg.solve(found.covariance, error)))
    squared = np.array(squared)
    assert 2.6 < squared.mean() < 3.5 and 0.91 < np.mean(squared < 7.815) < 0.98, (squared.mean(),
                                                                                     np.mean(squared < 7.815))


def test_heights_labels_and_backups(tmp_path):
    assert parse_heights("0-2.2") == (0.0, 2.2) and parse_heights("-0.5,2") == (-0.5, 2.0)
    for bad in ("2-1", "x", "0-nan", "1"):
        with pytest.raises(InputError, match="--heights"):
            parse_heights(bad)
    for bad in ("0-1e400", "nan-2"):  # not numbers to order: named as such, not as "the first must be below"
        with pytest.raises(InputError, match="give two finite heights"):
            parse_heights(bad)
    assert person_problem("p1") is None
    assert "a number" in person_problem("7") and "empty" in person_problem(" ") and "comma" in person_problem("a,b")
    sizes = {"rig01/narrow/f.png": (100, 80)}
    csv = tmp_path / "labels.csv"
    csv.write_text("image,x,y,person\nrig01/narrow/f.png,10,20,p1\nrig01/narrow/f.png,10,200,p2\n"
                   "rig01/narrow/f.png,1,2,3\nrig02/narrow/f.png,1,2,p1\nimage_a,x_a\n")
    labels, foreign = read_labels(csv, sizes)
    assert labels == [Label("rig01/narrow/f.png", 10.0, 20.0, "p1")]
    assert [row.line for row in foreign] == [3, 4, 5, 6]
    assert "outside" in foreign[0].why and "number" in foreign[1].why and "not a narrow image" in foreign[2].why
    original = csv.read_bytes()
    assert save_labels(csv, labels, foreign, backup=True) == tmp_path / "labels.csv.bak"
    assert read_labels(csv, sizes)[1] == foreign and (tmp_path / "labels.csv.bak").read_bytes() == original
    # A second, different backup never replaces the first.
    assert save_labels(csv, [], foreign, backup=True) == tmp_path / "labels.csv.bak2"
    assert (tmp_path / "labels.csv.bak").read_bytes() == original


@slow
@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(body=st.one_of(
    st.fixed_dictionaries({"frame": st.sampled_from(["frame0000.png", "x"]), "labels": st.lists(
        st.one_of(st.fixed_dictionaries({"image": st.sampled_from(["rig01/narrow/frame0000.png", "a"]),
                                         "x": st.one_of(st.floats(), st.integers(), st.text(max_size=2)),
                                         "y": st.one_of(st.floats(-10, 700), st.just(10 ** 400)),
                                         "person": st.one_of(st.text(max_size=3), st.integers(), st.none())}),
                  st.dictionaries(st.text(max_size=3), st.integers(), max_size=3), st.integers()), max_size=4)}),
    st.dictionaries(st.text(max_size=5), st.integers() | st.text(max_size=3), max_size=3)))
def test_the_api_answers_every_body(explorer, body):
    """Random JSON on PUT /api/labels and random band queries: a 200 or a 400 with a message, the server stays up."""
    host, port = explorer.httpd.server_address
    connection = http.client.HTTPConnection(host, port, timeout=30)
    connection.request("PUT", "/api/labels", json.dumps(body).encode(), {"Content-Type": "application/json"})
    answer = connection.getresponse()
    data = json.loads(answer.read())
    assert answer.status in (200, 400) and (answer.status == 200 or data["error"])
    query = urlencode({"view": str(body.get("frame", "0"))[:2], "x": "1e999", "y": "nan"})
    connection.request("GET", f"/api/band?{query}")
    answer = connection.getresponse()
    assert answer.status == 400 and json.loads(answer.read())["error"]


@pytest.fixture(scope="module")
def explorer(run, tmp_path_factory):
    _, out = run
    server = start_explorer(out, ExploreOptions(labels=tmp_path_factory.mktemp("fuzz") / "labels.csv"))
    yield server
    server.close()


@pytest.fixture(scope="module")
def two_frames(rendered, tmp_path_factory):
    """Two rigs, two synchronised frames, textured centre (a floor frame), run with the defaults."""
    from rigsfm.synth.scene import SceneOptions

    dataset = rendered(SceneOptions(num_rigs=2, arc_deg=60.0, image_scale=0.5, seed=4, frames_per_rig=2,
                                    textured_centre=True))
    out = tmp_path_factory.mktemp("two_frames") / "out"
    result = CliRunner().invoke(app, ["run", str(dataset.images), "--rigs", str(dataset.rigs), "--scale",
                                      str(dataset.scale), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


@slow
def test_frame_selector(two_frames, tmp_path):
    csv = tmp_path / "labels.csv"
    server = start_explorer(two_frames, ExploreOptions(frame="frame0001.png", labels=csv))
    try:
        with browser_page(server, "window.explore.ready", 1600, 1000) as page:
            assert page.eval_on_selector_all("#frame option", "o => o.map(x => x.value)") == ["frame0000.png",
                                                                                                "frame0001.png"]
            assert page.input_value("#frame") == "frame0001.png"
            assert "frame=frame0001.png" in page.get_attribute("#img-1", "src")
            assert page.evaluate("document.getElementById('img-1').naturalWidth") > 0
            click(page, 0, (400.0, 300.0))
            settle(page, 1)
            page.select_option("#frame", "frame0000.png")
            page.wait_for_function("window.explore.state.frame === 'frame0000.png'")
            assert "frame=frame0000.png" in page.get_attribute("#img-0", "src")
            assert page.locator("#persons tbody tr").count() == 0
            assert "1 label in other frames" in page.locator("#status").inner_text()
            click(page, 1, (300.0, 200.0))
            settle(page, 1)
        labels, _ = read_labels(csv, server.session.result.sizes)
        assert [(label.image, label.person) for label in labels] == [("rig01/narrow/frame0001.png", "p1"),
                                                                     ("rig02/narrow/frame0000.png", "p1")]
    finally:
        server.close()


def test_frames_the_run_was_not_given_are_named_as_not_shown(tmp_path, caplog):
    """A recording beside the run's images (associated with `rigsfm associate --poses-from`): the explorer offered
    the run's frames only, and said nothing of the others; it names them and what shows their persons instead."""
    import json
    import logging

    import cv2
    from test_camera_files import finished_workspace

    from rigsfm.explore.session import ExploreResult

    out, images = tmp_path / "out", tmp_path / "images"
    rec = finished_workspace(out)
    for image in rec.images.values():
        if "/narrow/" in image.name:
            for name in (image.name, image.name.rsplit("/", 1)[0] + "/later.png"):
                (images / name).parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(images / name), np.zeros((image.camera.height, image.camera.width), np.uint8))
    (out / "summary.json").write_text(json.dumps({"inputs": {"images": str(images)}}))
    with caplog.at_level(logging.WARNING, logger="rigsfm.explore.session"):
        result = ExploreResult(out)
    assert "later.png" not in result.frames
    assert "1 frame(s) beside the run's images that it was not given (later.png)" in caplog.text
    assert "--poses-from" in caplog.text
