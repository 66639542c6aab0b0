"""What several test modules share: independent reference computations (no Mitsuba inside), a JIT probe,
and random inputs of the shading operator with a backend-agreement check."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

from ngp_mi.camera import Camera
from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.render.shading import CameraLights, shade

ROOT = Path(__file__).resolve().parent.parent  # the repository
MAPS_TINY = ROOT / "train" / "maps_tiny.toml"
SHAPE_TINY = ROOT / "train" / "shape_tiny.toml"


def trimesh_depth(mesh: TriangleMesh, camera: Camera) -> np.ndarray:
    """z-depth (H, W) at pixel centres by trimesh's ray caster; 0 where the ray misses."""
    rays = camera.pixel_rays().reshape(-1, 3)
    directions = (rays / np.linalg.norm(rays, axis=1, keepdims=True)) @ camera.R  # camera -> world
    origins = np.broadcast_to(camera.position, directions.shape)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    locations, index_ray, _ = tm.ray.intersects_location(origins, directions, multiple_hits=False)
    depth = np.zeros(len(rays))
    depth[index_ray] = camera.world_to_camera(locations)[:, 2]
    return depth.reshape(camera.height, camera.width)


def rss_mib() -> float:
    """Resident memory of this process in MiB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2 ** 20


def analytic_sphere(camera: Camera, radius: float):
    """z-depth, camera-space normal and mask of a sphere at the origin, at pixel centres."""
    rays = camera.pixel_rays()
    unit = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    c = camera.world_to_camera(np.zeros(3))
    b = unit @ c
    disc = b ** 2 - (c @ c - radius ** 2)
    hit = disc > 0
    t = b - np.sqrt(np.where(hit, disc, 0.0))
    point = t[..., None] * unit
    return np.where(hit, point[..., 2], 0.0), np.where(hit[..., None], (point - c) / radius, 0.0), hit


def compiled_kernels(fn) -> tuple[list[dict], list[dict]]:
    """Run ``fn()`` and return (every JIT kernel it launched, those not found in Dr.Jit's kernel cache)."""
    from ngp_mi import backend

    dr = backend.drjit()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        fn()
        launched = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return launched, [k for k in launched if not k["cache_hit"]]


# ----------------------------------------------------------------------------- shading inputs

BACKENDS = ("drjit", "torch")


def random_inputs(n=2, h=5, w=6, dtype=torch.float64, seed=0, requires_grad=True):
    """Maps, per-batch camera-space lights (2 directional + 1 point) and cameras, all leaves."""
    g = torch.Generator().manual_seed(seed)
    normal = torch.randn(n, 3, h, w, generator=g, dtype=dtype)
    normal[:, 2] -= 1.5  # mostly facing the camera (camera space: -z towards the viewer)
    x = {
        "normal": normal,
        "albedo": torch.rand(n, 3, h, w, generator=g, dtype=dtype),
        "mask": (torch.rand(n, 1, h, w, generator=g, dtype=dtype) > 0.2).to(dtype),
        "depth": 1.5 + torch.rand(n, 1, h, w, generator=g, dtype=dtype),
        "alpha": 1.0 + 8 * torch.rand(n, 1, h, w, generator=g, dtype=dtype),
        "spec_albedo": torch.rand(n, 3, h, w, generator=g, dtype=dtype),
        "directions": torch.tensor([[[0.3, -0.8, -0.5], [-0.6, -0.4, -0.7]]], dtype=dtype).repeat(n, 1, 1)
        + 0.1 * torch.randn(n, 2, 3, generator=g, dtype=dtype),
        "irradiance": 0.5 + torch.rand(n, 2, 3, generator=g, dtype=dtype),
        "positions": torch.tensor([[[0.4, -1.0, 0.8]]], dtype=dtype).repeat(n, 1, 1),
        "intensity": 1.0 + torch.rand(n, 1, 3, generator=g, dtype=dtype),
    }
    for t in x.values():
        t.requires_grad_(requires_grad)
    cameras = [Camera.orbit(10.0 * i, 15.0 * i, (w, h)) for i in range(n)]
    return x, cameras


def shade_inputs(x, cameras, backend, mode="blinn_phong", view="per_pixel"):
    lights = CameraLights(x["directions"], x["irradiance"], x["positions"], x["intensity"])
    return shade(x["normal"], x["albedo"], x["mask"], lights, cameras, depth=x["depth"], alpha=x["alpha"],
                 spec_albedo=x["spec_albedo"], mode=mode, view=view, backend=backend)


def value_and_grads(backend, mode="blinn_phong", view="per_pixel", **inputs):
    """Shade float32 random inputs, backpropagate a weighted sum; return the image and every input's gradient."""
    x, cams = random_inputs(dtype=torch.float32, **inputs)
    out = shade_inputs(x, cams, backend, mode, view)
    (out * torch.linspace(-1, 2, out.numel()).reshape(out.shape)).sum().backward()
    return out.detach(), {k: v.grad for k, v in x.items()}


def assert_backends_agree(mode="blinn_phong", view="per_pixel", **inputs):
    """Values to 1e-5, gradients to 1e-5 of their largest magnitude (at least 1)."""
    (out, grads), (ref, ref_grads) = (value_and_grads(backend, mode, view, **inputs) for backend in BACKENDS)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    for name, g in ref_grads.items():
        if g is None:
            assert grads[name] is None or not grads[name].any()
            continue
        torch.testing.assert_close(grads[name], g, rtol=1e-5, atol=1e-5 * max(1.0, g.abs().max().item()), msg=name)


def run_torchrun(stage, config, port, processes=2):
    """``torchrun --nproc_per_node N -m ngp_mi.cli train STAGE --config CONFIG`` on CPUs (gloo), one
    thread each; the completed process."""
    env = {**os.environ, "NGP_MI_THREADS": "1", "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(processes),
                           "--master_port", str(port), "-m", "ngp_mi.cli", "train", stage, "--config", str(config)],
                          capture_output=True, text=True, timeout=600, env=env)


def run_cli(*args):
    """``ngp-mi ARGS`` in a new process (what a user runs); the completed process."""
    return subprocess.run([sys.executable, "-m", "ngp_mi.cli", *args], capture_output=True, text=True, timeout=300)


# ----------------------------------------------------------------------------- tiny training runs

def tiny_recipe(preset: Path, tmp_path: Path, name: str, file_name: str, **values) -> Path:
    """A copy of a tiny preset in ``tmp_path`` (data cached in ``tmp_path/data``, outputs in
    ``tmp_path/name``) with the given keys' values replaced (TOML text: strings quoted)."""
    stage = preset.stem.split("_")[0]
    text = preset.read_text().replace(f'cache_dir = "outputs/data/{stage}_tiny"', f'cache_dir = "{tmp_path / "data"}"')
    text = text.replace(f'out = "outputs/train/{stage}_tiny"', f'out = "{tmp_path / name}"')
    for key, value in values.items():
        text = text.replace(f"\n{key} = ", f"\n{key} = {value}\n# ", 1)
    path = tmp_path / file_name
    path.write_text(text)
    return path


def maps_recipe(tmp_path, name, iterations=6, **train):
    """train/maps_tiny.toml with ``iterations`` map steps and [train] values replaced."""
    return tiny_recipe(MAPS_TINY, tmp_path, name, f"{name}-{iterations}.toml", iterations=iterations, **train)


def shape_recipe(tmp_path, name, **train):
    """train/shape_tiny.toml with [train] values replaced."""
    return tiny_recipe(SHAPE_TINY, tmp_path, name, f"{name}.toml", **train)


def volume(vertices, faces):
    """Enclosed volume of a closed, outward-oriented mesh (divergence theorem)."""
    t = vertices[torch.as_tensor(np.asarray(faces), dtype=torch.long)]
    return (t[:, 0] * torch.linalg.cross(t[:, 1], t[:, 2])).sum() / 6


def worker_job(worker: int, progress, fail: int = -1) -> int:
    """A job for :func:`ngp_mi.data.workers.run_workers` tests (importable by spawned processes): 4
    items, 1 done before; fails in worker ``fail``."""
    progress.start(4, 1)
    if worker == fail:
        raise ValueError(f"worker {worker} was told to fail")
    progress.update(3)
    return 10 * worker


class Bar:
    """Stands in for a tqdm bar: counts what a job reports."""

    total, n = 0, 0

    def update(self, k):
        self.n += k


def sleeping_job(folder: str, worker: int, progress) -> None:
    """A worker that writes its pid to ``folder/<worker>.pid`` and sleeps (killed-parent tests)."""
    import os
    import time

    # Written under another name and renamed, so the test's glob never sees an empty pid file.
    Path(folder, f"{worker}.tmp").write_text(str(os.getpid()))
    Path(folder, f"{worker}.tmp").replace(Path(folder, f"{worker}.pid"))
    time.sleep(120)


class ExitingReconstruct:
    """A coarse-shape reconstruction whose process exits on its first shape (a worker dying, not a bad shape)."""

    meta = {"run": "exiting"}

    def __call__(self, grid):
        raise SystemExit("told to exit")


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie counts as ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False


def chromium_binary() -> str:
    """The headless browser `make test` installs (Debian's chromium)."""
    import shutil

    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    raise RuntimeError("no chromium found: `make test` installs Debian's chromium (scripts/ensure-chromium.sh)")


class Chromium:
    """A real headless Chromium driven over the DevTools protocol: navigate, evaluate, click, screenshots;
    ``errors`` collects what pages log as errors (console errors, exceptions, failed loads)."""

    def __init__(self, timeout: float = 60.0, size: tuple[int, int] = (1200, 800)):
        import json as _json
        import tempfile
        import time
        import urllib.request

        import websocket

        self._json, self.timeout, self.errors, self._ids = _json, timeout, [], iter(range(1, 10 ** 9))
        self.profile = tempfile.mkdtemp(prefix="chromium-")
        self.process = subprocess.Popen([chromium_binary(), "--headless=new", "--no-sandbox", "--disable-gpu",
                                         "--remote-debugging-port=0", f"--user-data-dir={self.profile}",
                                         f"--window-size={size[0]},{size[1]}", "--no-first-run", "about:blank"],
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        while not port_file.exists() or not port_file.read_text().strip():
            if time.monotonic() > deadline or self.process.poll() is not None:
                self.close()
                raise RuntimeError("chromium did not start")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        targets = _json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list").read())
        self.ws = websocket.create_connection(next(t for t in targets if t["type"] == "page")["webSocketDebuggerUrl"],
                                              timeout=timeout)
        for domain in ("Runtime", "Log", "Page"):
            self.call(f"{domain}.enable")

    def _note(self, message: dict) -> None:
        method, params = message.get("method"), message.get("params", {})
        if method == "Runtime.exceptionThrown":
            self.errors.append(params["exceptionDetails"].get("text", "exception"))
        elif method == "Runtime.consoleAPICalled" and params.get("type") == "error":
            self.errors.append(" ".join(str(a.get("value", a.get("description"))) for a in params.get("args", [])))
        elif method == "Log.entryAdded" and params["entry"]["level"] == "error":
            self.errors.append(f"{params['entry'].get('text')} {params['entry'].get('url', '')}")

    def call(self, method: str, **params) -> dict:
        own = next(self._ids)
        self.ws.send(self._json.dumps({"id": own, "method": method, "params": params}))
        while True:
            message = self._json.loads(self.ws.recv())
            if message.get("id") == own:
                return message.get("result", {})
            self._note(message)

    def navigate(self, url: str) -> None:
        """Open ``url`` and wait for its load event."""
        self.call("Page.navigate", url=url)
        while True:
            message = self._json.loads(self.ws.recv())
            if message.get("method") == "Page.loadEventFired":
                return
            self._note(message)

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def click(self, x: float, y: float) -> None:
        """A real mouse click at page coordinates."""
        for kind in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)

    def screenshot(self) -> np.ndarray:
        import base64
        import io

        from PIL import Image

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def drain(self, seconds: float = 0.5) -> None:
        """Read the page's events for a while (errors logged after the last call)."""
        import websocket

        self.ws.settimeout(seconds)
        try:
            while True:
                self._note(self._json.loads(self.ws.recv()))
        except websocket.WebSocketTimeoutException:
            pass
        finally:
            self.ws.settimeout(self.timeout)

    def close(self) -> None:
        import shutil

        if getattr(self, "ws", None) is not None:
            self.ws.close()
        self.process.kill()
        self.process.wait()
        shutil.rmtree(self.profile, ignore_errors=True)


def open_in_chromium(page: Path, timeout: float = 60.0) -> dict:
    """Load ``page`` in a real headless Chromium; returns every image of the page with whether it
    loaded (``images``: [(src, loaded)]) and what the page logged as an error (``errors``)."""
    browser = Chromium(timeout)
    try:
        browser.navigate(Path(page).resolve().as_uri())
        images = [tuple(x) for x in browser.evaluate(
            "Array.from(document.images).map(i => [i.getAttribute('src'), i.complete && i.naturalWidth > 0])")]
        browser.drain()
        return {"images": images, "errors": list(browser.errors)}
    finally:
        browser.close()


def without_encoder(folder, out):
    """A copy of a model folder as exported before G_shape's encoder was shipped."""
    import json

    from safetensors.torch import load_file, save_file

    from ngp_mi.models.pretrained import _sha256

    out.mkdir()
    for f in folder.iterdir():
        (out / f.name).write_bytes(f.read_bytes())
    tensors = {k: v for k, v in load_file(out / "shape.safetensors").items() if not k.startswith("shape.encoder.")}
    save_file(tensors, out / "shape.safetensors")
    card = json.loads((out / "card.json").read_text())
    card["files"]["shape.safetensors"]["sha256"] = _sha256(out / "shape.safetensors")
    (out / "card.json").write_text(json.dumps(card))
    return out
