"""``ngp-mi view``: NGP in the browser, every handle live, on viser (nerfstudio's viewer library).

The page shows a 3-D view: orbit, pan and zoom it, and the NGP image rendered from that camera fills
it (at a quarter of the pixels while the camera moves, in full when it stops). Lights are gizmos in
the scene (drag a directional light's direction or a point light's position); the panels set the
shape, the appearance, the variant, k_d / k_s / α, the map shown and the resolution, save the image
with its settings and write the settings as a ``generate`` command line.

:class:`ViewerState` is everything the page controls, without viser (the tests drive it directly);
:class:`Viewer` binds it to a viser server. Renders run on one worker thread; a request that arrives
while it renders replaces the one waiting, so dragging never queues work. Every stage result is kept
by :class:`ngp_mi.pipeline.NGPScene`: a light change re-runs only the shading.
"""

from __future__ import annotations

import dataclasses
import io
import json
import shlex
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ngp_mi.atomic import write_json
from ngp_mi.camera import Camera
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.lights import DirectionalLight, Light, PointLight, lights_to_json, overhead_rig
from ngp_mi.nets.networks import SIZE_MULTIPLE
from ngp_mi.pipeline import NGP, VARIANTS, NGPScene, display_maps, exemplar_image
from ngp_mi.render.shading import Constants
from ngp_mi.viz import chw_to_uint8, save_png

SHOWN = ("image", "depth", "normal", "albedo", "specular")


def camera_from_pose(wxyz: np.ndarray, position: np.ndarray, fov_y: float, width: int, height: int) -> Camera:
    """Our camera (world → camera ``[R | t]``, OpenCV axes) from a viewer pose: ``wxyz`` rotates camera
    axes into the world (OpenCV axes too: +Z forward, +Y down), ``fov_y`` the vertical field of view."""
    import viser.transforms as tf

    R = tf.SO3(np.asarray(wxyz, np.float64)).as_matrix().T
    focal = 0.5 * height / np.tan(0.5 * fov_y)
    return Camera(R=R, t=-R @ np.asarray(position, np.float64), width=width, height=height, focal_px=float(focal),
                  cx=width / 2.0, cy=height / 2.0)


def pose_of(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a camera: the inverse of :func:`camera_from_pose`."""
    import viser.transforms as tf

    return tf.SO3.from_matrix(camera.R.T).wxyz, camera.position


def _even(size: float) -> int:
    return max(8, int(round(size / SIZE_MULTIPLE)) * SIZE_MULTIPLE)


@dataclasses.dataclass
class Frame:
    image: np.ndarray  # uint8 (H, W, 3) of the map shown
    milliseconds: float
    stage_runs: dict[str, int]


class ViewerState:
    """What the viewer's page controls; every setter returns an error message for bad input (or None)."""

    def __init__(self, ngp: NGP, resolution: int = 128, model: str = "", mesh: str | TriangleMesh | None = None):
        self.ngp, self.model, self.resolution = ngp, model, resolution
        self.scene = NGPScene(ngp, resolution)
        self.shown = "image"
        self.shape: dict[str, Any] = {}
        self.appearance: dict[str, Any] = {"seed": 0}
        self.scene.set_appearance(seed=0)
        self.lights: list[Light] = overhead_rig()
        if mesh:
            error = self.load_mesh(mesh)
            if error:
                raise ValueError(error)
        elif ngp.shape_model is not None:
            self.set_shape_seed(0)
        else:
            raise ValueError("view: this model has no shape prior; give --mesh")

    # ---- shape and appearance
    def set_shape_seed(self, seed: int) -> str | None:
        self.scene.set_shape(seed=int(seed))
        self.shape = {"seed": int(seed)}
        return None

    def slerp_shapes(self, a: int, b: int, t: float) -> str | None:
        self.scene.interpolate_shapes(int(a), int(b), float(t))
        self.shape = {"interpolate": [int(a), int(b)], "t": float(t)}
        return None

    def load_mesh(self, path: str | TriangleMesh) -> str | None:
        """A mesh file (or a mesh in memory) as the shape."""
        try:
            self.scene.set_shape(mesh=path)
        except (ValueError, OSError) as exc:
            return f"could not load the mesh: {exc}"
        self.shape = {"mesh": str(path) if not isinstance(path, TriangleMesh) else "(a mesh in memory)"}
        return None

    def set_appearance_seed(self, seed: int) -> str | None:
        self.scene.set_appearance(seed=int(seed))
        self.appearance = {"seed": int(seed)}
        return None

    def slerp_appearance(self, a: int, b: int, t: float) -> str | None:
        self.scene.interpolate_appearance(int(a), int(b), float(t))
        self.appearance = {"interpolate": [int(a), int(b)], "t": float(t)}
        return None

    def set_exemplar(self, name: str, content: bytes) -> str | None:
        """An uploaded albedo image: its appearance code through E_da."""
        upload = io.BytesIO(content)
        upload.name = name
        try:
            exemplar = exemplar_image(upload, self.resolution)
        except ValueError as exc:
            return f"{name}: not an image ({exc})"
        self.scene.set_appearance(exemplar=exemplar)
        self.appearance = {"exemplar": name}
        return None

    # ---- lights, variant, constants, what is shown
    def set_lights(self, lights: list[Light]) -> str | None:
        self.lights = list(lights)  # each light checked its own values when it was made
        self.scene.set_lights(self.lights, self.scene.added_lights)
        return None

    def set_variant(self, variant: str) -> str | None:
        try:
            self.scene.set_variant(variant)
        except ValueError as exc:
            return str(exc)
        return None

    def set_constants(self, k_d: float, k_s: float, alpha: float) -> str | None:
        if not (0 <= k_d <= 10 and 0 <= k_s <= 10 and 0 < alpha <= 1000):
            return f"k_d, k_s must lie in [0, 10] and α in (0, 1000], got {k_d}, {k_s}, {alpha}"
        # R_diff's own k_diff (a trained model's) stays: the sliders are R_BP's
        self.scene.set_constants(Constants(float(k_d), float(k_s), float(alpha), self.scene.constants.k_diff))
        return None

    def set_shown(self, name: str) -> str | None:
        if name not in SHOWN:
            return f"map must be one of {SHOWN}, got {name!r}"
        self.shown = name
        return None

    def set_resolution(self, resolution: int) -> str | None:
        if not 16 <= resolution <= 1024:
            return f"resolution must lie in [16, 1024], got {resolution}"
        self.resolution = _even(resolution)
        return None

    # ---- rendering
    def camera_for(self, wxyz: np.ndarray, position: np.ndarray, fov_y: float, aspect: float,
                   preview: bool = False) -> Camera:
        """The camera of the viewer's pose at the state's resolution (half of it per side while moving)."""
        height = _even(self.resolution / (2 if preview else 1))
        return camera_from_pose(wxyz, position, fov_y, _even(height * aspect), height)

    def render(self, camera: Camera) -> Frame:
        start = time.perf_counter()
        self.scene.set_camera(camera)
        out = self.scene.render(maps=self.shown != "image")
        image = chw_to_uint8(out["image"]) if self.shown == "image" else display_maps(out)[self.shown]
        return Frame(image, 1e3 * (time.perf_counter() - start), dict(self.scene.stage_runs))

    # ---- what is kept
    def settings(self) -> dict[str, Any]:
        camera = self.scene.camera
        return {"model": self.model, "shape": self.shape, "appearance": self.appearance, "variant": self.scene.variant,
                "constants": dataclasses.asdict(self.scene.constants), "shown": self.shown,
                "resolution": self.resolution, "camera": camera.to_dict(),
                "lights": json.loads(lights_to_json(self.lights))}

    def generate_command(self, lights_file: str = "lights.json") -> str:
        """The ``ngp-mi generate`` line that renders this view (the lights go to ``lights_file``)."""
        position = self.scene.camera.position
        theta = float(np.degrees(np.arcsin(position[1] / np.linalg.norm(position))))
        phi = float(np.degrees(np.arctan2(position[0], position[2])))
        args = ["ngp-mi", "generate", "--model", self.model or "chair", "--out", "outputs/view",
                "--views", f"{theta:.2f},{phi:.2f}", "--res", str(_even(self.resolution)),
                "--variant", self.scene.variant.replace("_", "-"), "--lights", lights_file]
        if "mesh" in self.shape:
            args += ["--mesh", self.shape["mesh"]]
        elif "seed" in self.shape:
            args += ["--seed", str(self.shape["seed"]), "--num", "1"]
        return shlex.join(args)

    def save(self, folder: str | Path, frame: Frame) -> Path:
        """The frame as PNG with its settings (JSON) and the lights as a lights file; returns the PNG."""
        folder = Path(folder)
        stem = time.strftime("view-%Y%m%d-%H%M%S")
        png = save_png(folder / f"{stem}.png", frame.image)
        write_json(folder / f"{stem}.json", {**self.settings(), "generate": self.generate_command(f"{stem}.lights.json")})
        write_json(folder / f"{stem}.lights.json", json.loads(lights_to_json(self.lights)))
        return png


class LatestOnly:
    """One worker thread running the newest request: a request that arrives while it works replaces
    the one waiting (dragging never queues renders)."""

    def __init__(self, work: Callable[[Any], None]):
        self.work = work
        self.pending: Any = None
        self.condition = threading.Condition()
        self.stopped = False
        self.thread = threading.Thread(target=self._run, name="ngp-view-render", daemon=True)
        self.thread.start()

    def submit(self, request: Any) -> None:
        with self.condition:
            self.pending = request
            self.condition.notify()

    def stop(self) -> None:
        with self.condition:
            self.stopped = True
            self.condition.notify()
        self.thread.join(timeout=10)

    def _run(self) -> None:
        while True:
            with self.condition:
                while self.pending is None and not self.stopped:
                    self.condition.wait()
                if self.stopped:
                    return
                request, self.pending = self.pending, None
            self.work(request)


class Viewer:
    """:class:`ViewerState` on a viser server: the 3-D view, light gizmos and panels."""

    def __init__(self, state: ViewerState, host: str = "127.0.0.1", port: int = 8080, out: str | Path = "outputs/view"):
        import viser  # the viewer's library, imported only by the viewer

        self.state, self.out = state, Path(out)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+y")
        self.lock = threading.Lock()  # the state is used by the render thread and the GUI callbacks
        self.poses: dict[int, tuple[np.ndarray, np.ndarray, float, float]] = {}
        self.settle: dict[int, threading.Timer] = {}
        self.last_frame: Frame | None = None
        self.renderer = LatestOnly(self._render)
        self._build_gui()
        self._place_light_gizmos()
        self.server.on_client_connect(self._connected)

    # ---- rendering
    def _connected(self, client: Any) -> None:
        wxyz, position = pose_of(self.state.scene.camera)
        client.camera.position = position
        client.camera.look_at = (0.0, 0.0, 0.0)
        client.camera.up_direction = (0.0, 1.0, 0.0)
        client.camera.fov = float(2 * np.arctan(0.5 * self.state.scene.camera.height / self.state.scene.camera.focal_px))
        client.camera.on_update(lambda camera: self._camera_moved(client))

    def _camera_moved(self, client: Any) -> None:
        camera = client.camera
        aspect = camera.aspect if camera.aspect > 0 else 1.0
        self.poses[client.client_id] = (np.asarray(camera.wxyz), np.asarray(camera.position), float(camera.fov), aspect)
        self.renderer.submit((client, True))
        if client.client_id in self.settle:
            self.settle[client.client_id].cancel()
        timer = threading.Timer(0.3, lambda: self.renderer.submit((client, False)))  # the camera stopped: full size
        timer.daemon = True
        self.settle[client.client_id] = timer
        timer.start()

    def refresh(self) -> None:
        """Render again for every client (a handle changed)."""
        for client in self.server.get_clients().values():
            self.renderer.submit((client, False))

    def _render(self, request: tuple[Any, bool]) -> None:
        client, preview = request
        pose = self.poses.get(client.client_id)
        try:
            with self.lock:
                camera = (self.state.camera_for(*pose, preview=preview) if pose is not None
                          else self.state.scene.camera)
                frame = self.state.render(camera)
            client.scene.set_background_image(frame.image, format="jpeg")
            self.last_frame = frame
            self.status.content = (f"{frame.image.shape[1]}×{frame.image.shape[0]} {self.state.shown}: "
                                   f"{frame.milliseconds:.1f} ms{' (moving)' if preview else ''}")
        except Exception as exc:  # the server keeps running; the page says what failed
            self.message(f"render failed: {type(exc).__name__}: {exc}")

    def message(self, text: str | None) -> None:
        self.messages.content = text or ""

    def _apply(self, change: Callable[[], str | None]) -> None:
        """Run a state change from the page; show its error, or render again."""
        try:
            with self.lock:
                error = change()
        except (ValueError, TypeError) as exc:
            error = str(exc)
        self.message(error)
        if error is None:
            self.refresh()

    # ---- lights
    def _place_light_gizmos(self) -> None:
        self.server.scene.remove_by_name("/lights")
        self.gizmos = []
        for i, light in enumerate(self.state.lights):
            where = np.asarray(light.position if isinstance(light, PointLight) else light.direction)
            colour = np.asarray(light.intensity if isinstance(light, PointLight) else light.irradiance)
            gizmo = self.server.scene.add_transform_controls(f"/lights/{i}", scale=0.25, disable_rotations=True,
                                                             position=tuple(where * (1.0 if isinstance(light, PointLight)
                                                                                     else 1.5)))
            self.server.scene.add_icosphere(f"/lights/{i}/bulb", radius=0.05,
                                            color=tuple(int(255 * min(1.0, c / max(colour.max(), 1e-6))) for c in colour))
            gizmo.on_update(lambda event, i=i: self._apply(lambda: self._move_light(i, event.target.position)))
            self.gizmos.append(gizmo)
        self.light_index.options = [str(i) for i in range(len(self.state.lights))] or ["-"]

    def _move_light(self, i: int, position: np.ndarray) -> str | None:
        lights = list(self.state.lights)
        light = lights[i]
        lights[i] = (PointLight(tuple(position), light.intensity) if isinstance(light, PointLight)
                     else DirectionalLight(tuple(position), light.irradiance))
        return self.state.set_lights(lights)

    def _recolour_light(self) -> str | None:
        if not self.state.lights:
            return "no light to colour: add one"
        i = int(self.light_index.value)
        rgb = np.asarray(self.light_colour.value, np.float64) / 255.0 * float(self.light_power.value)
        lights = list(self.state.lights)
        light = lights[i]
        lights[i] = (PointLight(light.position, tuple(rgb)) if isinstance(light, PointLight)
                     else DirectionalLight(light.direction, tuple(rgb)))
        return self.state.set_lights(lights)

    def _edit_lights(self, lights: list[Light]) -> None:
        self._apply(lambda: self.state.set_lights(lights))
        self._place_light_gizmos()

    # ---- panels
    def _build_gui(self) -> None:
        gui, state = self.server.gui, self.state
        self.status = gui.add_markdown("starting…")
        self.messages = gui.add_markdown("")
        with gui.add_folder("Shape"):
            if state.ngp.shape_model is not None:
                seed = gui.add_number("shape seed", 0, step=1)
                seed.on_update(lambda _: self._apply(lambda: state.set_shape_seed(int(seed.value))))
                a, b = gui.add_number("slerp from seed", 0, step=1), gui.add_number("to seed", 1, step=1)
                t = gui.add_slider("slerp t", 0.0, 1.0, 0.05, 0.0)
                t.on_update(lambda _: self._apply(lambda: state.slerp_shapes(int(a.value), int(b.value), t.value)))
            path = gui.add_text("mesh file", "")
            gui.add_button("load mesh").on_click(lambda _: self._apply(lambda: state.load_mesh(path.value)))
        with gui.add_folder("Appearance"):
            look = gui.add_number("appearance seed", 0, step=1)
            look.on_update(lambda _: self._apply(lambda: state.set_appearance_seed(int(look.value))))
            a2, b2 = gui.add_number("slerp from z_da seed", 0, step=1), gui.add_number("to z_da seed", 1, step=1)
            t2 = gui.add_slider("z_da slerp t", 0.0, 1.0, 0.05, 0.0)
            t2.on_update(lambda _: self._apply(lambda: state.slerp_appearance(int(a2.value), int(b2.value), t2.value)))
            upload = gui.add_upload_button("exemplar image", mime_type="image/*")
            upload.on_upload(lambda _: self._apply(lambda: state.set_exemplar(upload.value.name, upload.value.content)))
            gui.add_button("reset appearance").on_click(
                lambda _: self._apply(lambda: state.set_appearance_seed(int(look.value))))
        with gui.add_folder("Lights"):
            self.light_index = gui.add_dropdown("light", ["0"])
            self.light_colour = gui.add_rgb("colour", (255, 255, 255))
            self.light_power = gui.add_number("intensity", 0.5, min=0.0, max=100.0, step=0.1)
            gui.add_button("apply colour").on_click(lambda _: self._apply(self._recolour_light))
            gui.add_button("add directional light").on_click(lambda _: self._edit_lights(
                [*state.lights, DirectionalLight((0.0, 1.0, 1.0), (0.5, 0.5, 0.5))]))
            gui.add_button("add point light").on_click(lambda _: self._edit_lights(
                [*state.lights, PointLight((0.0, 1.0, 1.2), (1.0, 1.0, 1.0))]))
            gui.add_button("remove light").on_click(lambda _: self._edit_lights(
                [l for k, l in enumerate(state.lights) if str(k) != self.light_index.value]))
            gui.add_button("overhead rig").on_click(lambda _: self._edit_lights(overhead_rig()))
        with gui.add_folder("Rendering"):
            variant = gui.add_dropdown("variant", [v for v in VARIANTS if state.ngp.specular is not None
                                                   or v in ("ngp_bp", "no_sp")], initial_value=state.scene.variant
                                       if state.ngp.specular is not None else "ngp_bp")
            variant.on_update(lambda _: self._apply(lambda: state.set_variant(variant.value)))
            if state.ngp.specular is None:
                state.set_variant("ngp_bp")
            c = state.scene.constants
            k_d, k_s = gui.add_slider("k_d", 0.0, 1.0, 0.05, c.k_d), gui.add_slider("k_s", 0.0, 1.0, 0.05, c.k_s)
            alpha = gui.add_slider("alpha", 1.0, 64.0, 1.0, c.alpha)
            for handle in (k_d, k_s, alpha):
                handle.on_update(lambda _: self._apply(lambda: state.set_constants(k_d.value, k_s.value, alpha.value)))
            shown = gui.add_dropdown("show", list(SHOWN), initial_value="image")
            shown.on_update(lambda _: self._apply(lambda: state.set_shown(shown.value)))
            size = gui.add_dropdown("resolution", ["64", "128", "256", "512"], initial_value=str(state.resolution)
                                    if str(state.resolution) in ("64", "128", "256", "512") else "128")
            size.on_update(lambda _: self._apply(lambda: state.set_resolution(int(size.value))))
            gui.add_button("save image").on_click(lambda _: self._save())
            command = gui.add_text("generate command", "")
            gui.add_button("write generate command").on_click(
                lambda _: setattr(command, "value", state.generate_command()))

    def _save(self) -> None:
        if self.last_frame is None:
            self.message("nothing rendered yet")
            return
        with self.lock:
            path = self.state.save(self.out, self.last_frame)
        self.message(f"saved {path} (with its settings and lights)")

    def stop(self) -> None:
        for timer in self.settle.values():
            timer.cancel()
        self.renderer.stop()
        self.server.stop()


def view(model: str | None = None, mesh: str | None = None, maps_run: str | None = None, shape_run: str | None = None,
         host: str = "127.0.0.1", port: int = 8080, resolution: int = 128, out: str = "outputs/view",
         log: Callable[[str], None] = print) -> None:
    """``ngp-mi view``: serve the viewer until interrupted."""
    ngp = NGP(maps_run, shape_run) if maps_run else NGP.pretrained(model or "chair")
    viewer = Viewer(ViewerState(ngp, resolution, model=model or ("" if maps_run else "chair"), mesh=mesh), host, port, out)
    log(f"view: open http://{host}:{port} (Ctrl-C stops)")
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
