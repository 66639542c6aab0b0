"""The Dr.Jit op's own machinery: pixels per lane, recorded (frozen) kernels, memory, packet alignment."""

import pytest
import torch
from helpers import BACKENDS, assert_backends_agree, compiled_kernels, random_inputs, rss_mib, value_and_grads

from ngp_mi.camera import Camera
from ngp_mi.lights import overhead_rig
from ngp_mi.render.shading import CameraLights, shade


@pytest.mark.parametrize("freeze", [True, False])
@pytest.mark.parametrize("width", [5, 6, 8])  # 1, 2 and 4 pixels per kernel lane
def test_every_row_width_agrees_with_torch(width, freeze, monkeypatch):
    from ngp_mi.render.shading import drjit_op

    monkeypatch.setattr(drjit_op, "FREEZE", freeze)
    assert_backends_agree(n=2, h=3, w=width, seed=width)


def test_replayed_kernels_give_new_inputs_right_values_and_gradients():
    """The Dr.Jit op records its kernels once per layout (``dr.freeze``); later calls replay them with
    the new arrays. Each call must see its own inputs, and replaying must trace and compile nothing."""
    from ngp_mi.render.shading import drjit_op

    shape = {"n": 2, "h": 4, "w": 8}
    value_and_grads("drjit", seed=100, **shape)  # records; so does the call below: Dr.Jit's flags are in the key
    compiled_kernels(lambda: value_and_grads("drjit", seed=101, **shape))
    frozen = [drjit_op.RECORDINGS[name] for name in ("_shade_forward", "_shade_backward")]
    recordings = [f.n_recordings for f in frozen]
    for seed in (1, 2, 3):
        launched, compiled = compiled_kernels(lambda: value_and_grads("drjit", seed=seed, **shape))
        assert len(launched) == 2 and not compiled  # one forward and one backward kernel, from the cache
        assert_backends_agree(seed=seed, **shape)
    assert [f.n_recordings for f in frozen] == recordings


def test_repeated_calls_do_not_grow_memory():
    """Recorded kernels are replayed with each call's arrays; nothing may accumulate per call."""
    cams = [Camera.orbit(10.0, -60.0 + 15 * i, 32) for i in range(4)]

    def step(seed):
        g = torch.Generator().manual_seed(seed)
        normal = torch.randn(4, 3, 32, 32, generator=g).requires_grad_()
        albedo = torch.rand(4, 3, 32, 32, generator=g).requires_grad_()
        lights = CameraLights.from_lights(overhead_rig(), cams)
        lights.irradiance.requires_grad_()
        shade(normal, albedo, None, lights, cams).mean().backward()

    for seed in range(30):
        step(seed)
    before = rss_mib()
    for seed in range(300):
        step(seed)
    assert rss_mib() - before < 5, f"RSS grew by {rss_mib() - before:.1f} MiB over 300 calls"


def test_maps_that_start_off_a_packet_boundary():
    """Views into a larger tensor may start at any element; the kernel's packet loads must not care."""
    x, cams = random_inputs(n=2, h=4, w=8, dtype=torch.float32, seed=7)
    storage = torch.zeros(1 + x["normal"].numel())
    storage[1:] = x["normal"].detach().reshape(-1)
    for backend in BACKENDS:
        x[f"normal_{backend}"] = storage[1:].view(x["normal"].shape).requires_grad_()
    assert x["normal_drjit"].data_ptr() % 16 != 0
    results = {}
    for backend in BACKENDS:
        lights = CameraLights(x["directions"], x["irradiance"], x["positions"], x["intensity"])
        out = shade(x[f"normal_{backend}"], x["albedo"], x["mask"], lights, cams, depth=x["depth"], backend=backend)
        (out * torch.linspace(-1, 2, out.numel()).reshape(out.shape)).sum().backward()
        results[backend] = (out.detach(), x[f"normal_{backend}"].grad)
    for a, b in zip(results["drjit"], results["torch"]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
