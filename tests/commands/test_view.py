"""ngp-mi view: the viewer's state without a browser, then the page in a real headless Chromium."""

import dataclasses
import io
import json
import socket
import threading
import time

import numpy as np
import pytest
from helpers import Chromium
from PIL import Image

from ngp_mi.camera import Camera
from ngp_mi.cli import main
from ngp_mi.commands.view import LatestOnly, Viewer, ViewerState, camera_from_pose, pose_of
from ngp_mi.lights import PointLight, overhead_rig
from ngp_mi.pipeline import NGP
from ngp_mi.render.shading import Constants


@pytest.fixture(scope="module")
def ngp(tiny_model):
    return NGP.pretrained(tiny_model)


@pytest.fixture
def box(box_obj):
    return box_obj


@pytest.mark.parametrize("theta, phi", [(10.0, -30.0), (0.0, 0.0), (20.0, 90.0), (-15.0, 170.0)])
def test_a_viewer_pose_is_the_camera_it_came_from(theta, phi):
    camera = Camera.orbit(theta, phi, 64)
    wxyz, position = pose_of(camera)
    back = camera_from_pose(wxyz, position, 2 * np.arctan(32 / camera.focal_px), 64, 64)
    np.testing.assert_allclose(back.R, camera.R, atol=1e-9)
    np.testing.assert_allclose(back.t, camera.t, atol=1e-9)
    assert back.focal_px == pytest.approx(camera.focal_px)


def test_the_state_takes_every_handle_and_names_bad_input(ngp, box, tmp_path):
    state = ViewerState(ngp, 32, model="tiny", mesh=str(box))
    first = state.render(state.scene.camera)
    runs = dict(first.stage_runs)
    assert state.set_lights([*overhead_rig(), PointLight((0.0, 1.0, 1.0), (3.0, 1.0, 1.0))]) is None
    lit = state.render(state.scene.camera)
    assert {k: v - runs[k] for k, v in lit.stage_runs.items() if v != runs[k]} == {"shade": 1, "blend": 1}
    assert not np.array_equal(lit.image, first.image)
    assert "not.png: not an image" in state.set_exemplar("not.png", b"definitely not a PNG")
    png = io.BytesIO()
    Image.fromarray(np.full((16, 16, 3), 200, np.uint8)).save(png, format="PNG")
    assert state.set_exemplar("grey.png", png.getvalue()) is None and state.appearance == {"exemplar": "grey.png"}
    assert "could not load the mesh" in state.load_mesh(str(tmp_path / "missing.obj"))
    assert state.shape == {"mesh": str(box)}  # unchanged
    assert "k_d, k_s must lie in" in state.set_constants(0.8, 0.2, -1.0)
    state.scene.set_constants(dataclasses.replace(state.scene.constants, k_diff=1.0))  # a model with R_diff's own k_d
    assert state.set_constants(0.6, 0.4, 8.0) is None and state.scene.constants == Constants(0.6, 0.4, 8.0, 1.0)
    assert "map must be one of" in state.set_shown("colour")
    for shown in ("depth", "normal", "albedo", "specular"):
        assert state.set_shown(shown) is None and state.render(state.scene.camera).image.shape == (32, 32, 3)
    assert state.set_resolution(5) is not None and state.set_resolution(100) is None and state.resolution == 100


def test_save_writes_the_image_its_settings_and_a_generate_line_that_redraws_it(ngp, box, tiny_model, tmp_path):
    state = ViewerState(ngp, 32, model=str(tiny_model), mesh=str(box))
    state.set_appearance_seed(3)
    frame = state.render(state.scene.camera)  # the default camera: θ 10°, φ −30° on the paper's orbit
    png = state.save(tmp_path / "saved", frame)
    settings = json.loads(png.with_suffix(".json").read_text())
    assert settings["appearance"] == {"seed": 3} and settings["shape"] == {"mesh": str(box)}
    command = settings["generate"].split()
    assert command[:2] == ["ngp-mi", "generate"]
    argv = command[1:]
    argv[argv.index("--out") + 1] = str(tmp_path / "again")
    argv[argv.index("--lights") + 1] = str(png.parent / argv[argv.index("--lights") + 1])
    argv += ["--seed", "3"]  # the appearance seed of the only shape
    assert main(argv) == 0
    again = np.asarray(Image.open(next((tmp_path / "again" / "images").glob("*.png"))))
    assert np.abs(again.astype(int) - frame.image.astype(int)).max() <= 1


def test_requests_that_arrive_while_rendering_replace_the_waiting_one():
    done, gate = [], threading.Event()

    def work(request):
        gate.wait(5)
        done.append(request)

    worker = LatestOnly(work)
    worker.submit(0)
    time.sleep(0.1)  # 0 is being rendered
    for request in range(1, 6):
        worker.submit(request)
    gate.set()
    time.sleep(0.3)
    worker.stop()
    assert done == [0, 5]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_page_changes_the_image_when_a_light_and_the_appearance_change(ngp, box, tmp_path):
    port = _free_port()
    viewer = Viewer(ViewerState(ngp, 64, model="tiny", mesh=str(box)), port=port, out=tmp_path)
    browser = Chromium()
    try:
        browser.navigate(f"http://127.0.0.1:{port}/")

        def wait_for(condition, what, seconds=60.0):
            deadline = time.monotonic() + seconds
            while not condition():
                assert time.monotonic() < deadline, what
                time.sleep(0.2)

        def view_pixels():
            return browser.screenshot()[100:700, 100:800].astype(int)  # the 3-D view, left of the panel

        def rendered():  # a full-size frame is on the page
            text = browser.evaluate("document.body.innerText") or ""
            return "image:" in text and "(moving)" not in text

        def click(label):
            box_ = browser.evaluate(f"""(() => {{
                const b = [...document.querySelectorAll('button')].find(b => b.innerText.trim() === {label!r});
                b.scrollIntoView(); const r = b.getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2];
            }})()""")
            browser.click(*box_)

        wait_for(rendered, "the first frame never arrived")
        time.sleep(1.0)
        before = view_pixels()
        # the appearance seed: the number input's increment chevron, clicked like a user
        up = browser.evaluate("""(() => {
            const label = [...document.querySelectorAll('label')].find(l => l.innerText.trim() === 'appearance seed');
            const all = [...document.querySelectorAll('label, input, button')];
            const button = all.slice(all.indexOf(label)).find(e => e.tagName === 'BUTTON');
            button.scrollIntoView(); const r = button.getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2];
        })()""")
        browser.click(*up)
        wait_for(lambda: viewer.state.appearance == {"seed": 1}, "the appearance seed did not change")
        time.sleep(1.5)
        after_look = view_pixels()
        assert np.abs(after_look - before).mean() > 0.5
        click("add point light")
        wait_for(lambda: len(viewer.state.lights) == 5, "no light was added")
        time.sleep(1.5)
        after_light = view_pixels()
        assert np.abs(after_light - after_look).mean() > 0.5
        browser.drain()
        assert browser.errors == []
    finally:
        browser.close()
        viewer.stop()


def test_the_viewer_starts_on_the_shipped_chair_when_no_model_is_named(monkeypatch):
    """`ngp-mi view` with no model serves the shipped chair (the server itself is the browser test's)."""
    import ngp_mi.commands.view as module

    started = {}

    class Recorder:
        def __init__(self, state, *args):
            started["state"] = state

        def stop(self):
            started["stopped"] = True

    def interrupt(seconds):
        raise KeyboardInterrupt

    monkeypatch.setattr(module, "Viewer", Recorder)
    monkeypatch.setattr(module.time, "sleep", interrupt)
    module.view(log=lambda *_: None)
    state = started["state"]
    assert started["stopped"] and state.model == "chair" and state.scene.ngp.card["family"] == "chair"
    assert state.render(state.scene.camera) is not None
