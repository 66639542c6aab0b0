"""Pinhole cameras in OpenCV axes, the paper's view distribution, and conversion to Mitsuba sensors.

Conventions (README "Conventions"):

* World: +Y up, objects face +Z and are normalised around the origin (``geometry.mesh``).
* A camera maps a world point ``p`` to camera space ``x_c = R p + t`` with OpenCV axes
  (x right, y down, z forward) and to pixels ``u ~ K x_c``. ``E = [R | t]`` is world→camera.
  Pixel ``(i, j)`` covers ``[i, i+1) × [j, j+1)``; its centre is ``(i + 0.5, j + 0.5)``.
* The paper's view distribution (App. C): the camera sits on a sphere of radius ρ = 2 at
  elevation θ (above the horizontal plane) and azimuth φ (about +Y, from the object's face
  direction +Z towards +X), looks at the origin with no roll; θ ∈ [0°, 20°], φ ∈ [−90°, 90°].
  The lens is 50 mm on 36 mm film (horizontal field of view 2·atan(18/50) ≈ 39.6°).

The image's "right" axis is taken as the limit of ``forward × up`` for θ → ±90°, which is
``(cos φ, 0, −sin φ)`` for every θ, so looking straight down (θ = 90°) is well defined.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from ngp_mi import backend

PAPER_RADIUS = 2.0
PAPER_FOCAL_MM = 50.0
PAPER_FILM_MM = 36.0
PAPER_THETA_RANGE = (0.0, 20.0)
PAPER_PHI_RANGE = (-90.0, 90.0)

# Mitsuba's camera frame is (left, up, forward); OpenCV's is (right, down, forward).
_OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0])


def _as_matrix(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"camera {name} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"camera {name} has non-finite entries: {array.tolist()}")
    return array


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera with square pixels.

    Attributes:
        R, t: world→camera rotation (3×3) and translation (3,), OpenCV axes.
        width, height: image size in pixels.
        focal_px: focal length in pixels (``K[0,0] = K[1,1]``).
        cx, cy: principal point in pixels (image centre: ``width/2, height/2``).
        theta_deg, phi_deg: orbit angles when built by :meth:`orbit`, else ``None`` (metadata).
    """

    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    focal_px: float
    cx: float
    cy: float
    theta_deg: float | None = None
    phi_deg: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", _as_matrix(self.R, (3, 3), "R"))
        object.__setattr__(self, "t", _as_matrix(self.t, (3,), "t"))
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-6) or np.linalg.det(self.R) < 0:
            raise ValueError("camera R must be a rotation (orthonormal, det +1)")
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"camera {name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        if not (math.isfinite(self.focal_px) and self.focal_px > 0):
            raise ValueError(f"camera focal_px must be positive and finite, got {self.focal_px!r}")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def orbit(cls, theta_deg: float, phi_deg: float, resolution: int | tuple[int, int] = 256,
              radius: float = PAPER_RADIUS, focal_mm: float = PAPER_FOCAL_MM,
              film_mm: float = PAPER_FILM_MM) -> "Camera":
        """Camera on a sphere of ``radius`` at elevation θ and azimuth φ, looking at the origin (App. C).

        ``film_mm`` is the horizontal film width, so ``focal_px = focal_mm / film_mm · width``.
        """
        theta_deg, phi_deg = float(theta_deg), float(phi_deg)
        if not (math.isfinite(theta_deg) and math.isfinite(phi_deg)):
            raise ValueError(f"camera angles must be finite, got theta={theta_deg}, phi={phi_deg}")
        if abs(theta_deg) > 90.0:
            raise ValueError(f"camera elevation theta must lie in [-90, 90] degrees, got {theta_deg}")
        if not (radius > 0 and focal_mm > 0 and film_mm > 0):
            raise ValueError(f"radius, focal_mm and film_mm must be positive, got {radius}, {focal_mm}, {film_mm}")
        width, height = (resolution, resolution) if np.isscalar(resolution) else tuple(resolution)
        theta, phi = math.radians(theta_deg), math.radians(phi_deg)
        eye = radius * np.array([math.cos(theta) * math.sin(phi), math.sin(theta), math.cos(theta) * math.cos(phi)])
        forward = -eye / radius
        right = np.array([math.cos(phi), 0.0, -math.sin(phi)])
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])
        return cls(R=R, t=-R @ eye, width=width, height=height, focal_px=focal_mm / film_mm * width,
                   cx=width / 2.0, cy=height / 2.0, theta_deg=theta_deg, phi_deg=phi_deg)

    @classmethod
    def from_K_E(cls, K: Any, E: Any, width: int, height: int) -> "Camera":
        """Camera from OpenCV intrinsics ``K`` (3×3, square pixels, no skew) and extrinsics ``E`` (3×4)."""
        K = _as_matrix(K, (3, 3), "K")
        E = _as_matrix(E, (3, 4), "E")
        if not math.isclose(K[0, 0], K[1, 1], rel_tol=1e-6) or K[0, 1] != 0 or np.any(K[2] != [0, 0, 1]):
            raise ValueError(f"camera K must have fx == fy, no skew and last row [0, 0, 1], got {K.tolist()}")
        return cls(R=E[:, :3], t=E[:, 3], width=width, height=height, focal_px=K[0, 0], cx=K[0, 2], cy=K[1, 2])

    def with_resolution(self, width: int, height: int | None = None) -> "Camera":
        """The same view at another resolution (focal length and principal point scale with the width)."""
        height = width if height is None else height
        s = width / self.width
        return dataclasses.replace(self, width=width, height=height, focal_px=self.focal_px * s,
                                   cx=self.cx * s, cy=self.cy * height / self.height)

    # ------------------------------------------------------------------ matrices
    @property
    def K(self) -> np.ndarray:
        """Intrinsics in pixels, OpenCV convention."""
        return np.array([[self.focal_px, 0.0, self.cx], [0.0, self.focal_px, self.cy], [0.0, 0.0, 1.0]])

    @property
    def E(self) -> np.ndarray:
        """Extrinsics ``[R | t]``, world→camera (3×4)."""
        return np.concatenate([self.R, self.t[:, None]], axis=1)

    @property
    def position(self) -> np.ndarray:
        """Camera centre in world space, ``−Rᵀ t``."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> np.ndarray:
        """Optical axis (unit, world space)."""
        return self.R[2].copy()

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view in degrees (for a centred principal point)."""
        return math.degrees(2.0 * math.atan(self.width / (2.0 * self.focal_px)))

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) → camera-space points (..., 3), OpenCV axes."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (..., 3) → (pixel coordinates (..., 2), z-depth (...)), i.e. ``K E p``."""
        xc = self.world_to_camera(points)
        z = xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.focal_px * xc[..., 0] / z + self.cx, self.focal_px * xc[..., 1] / z + self.cy], -1)
        return uv, z

    def pixel_rays(self) -> np.ndarray:
        """Camera-space directions through every pixel centre, (height, width, 3), with z = 1."""
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        uu, vv = np.meshgrid(u, v)
        return np.stack([(uu - self.cx) / self.focal_px, (vv - self.cy) / self.focal_px, np.ones_like(uu)], -1)

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly description (K, E, size and the orbit angles when known)."""
        return {"K": self.K.tolist(), "E": self.E.tolist(), "width": self.width, "height": self.height,
                "theta_deg": self.theta_deg, "phi_deg": self.phi_deg}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Camera":
        camera = cls.from_K_E(data["K"], data["E"], data["width"], data["height"])
        return dataclasses.replace(camera, theta_deg=data.get("theta_deg"), phi_deg=data.get("phi_deg"))

    # ------------------------------------------------------------------ Mitsuba
    def camera_to_world_mitsuba(self) -> np.ndarray:
        """4×4 camera→world matrix in Mitsuba's camera axes (x left, y up, z forward)."""
        M = np.eye(4)
        M[:3, :3] = self.R.T @ _OPENCV_TO_MITSUBA
        M[:3, 3] = self.position
        return M

    def to_mitsuba(self, spp: int = 1, rfilter: str = "box", pixel_format: str = "rgb",
                   sampler: str = "independent", seed: int = 0) -> dict[str, Any]:
        """A ``perspective`` sensor dictionary for ``mi.load_dict`` with the same K and E.

        ``spp = 1`` with a ``box`` filter and an ``independent`` sampler jitters inside the pixel;
        for geometric maps sampled exactly at pixel centres use the G-buffer renderer instead.
        """
        mi = backend.mitsuba()
        return {
            "type": "perspective",
            "fov": self.hfov_deg,
            "fov_axis": "x",
            # Mitsuba's offsets are in film units and point the other way from OpenCV's (cx, cy).
            "principal_point_offset_x": (self.width / 2.0 - self.cx) / self.width,
            "principal_point_offset_y": (self.height / 2.0 - self.cy) / self.height,
            "near_clip": 1e-3,
            "far_clip": 1e4,
            "to_world": mi.ScalarTransform4f(self.camera_to_world_mitsuba().tolist()),
            "film": {"type": "hdrfilm", "width": self.width, "height": self.height,
                     "rfilter": {"type": rfilter}, "pixel_format": pixel_format},
            "sampler": {"type": sampler, "sample_count": int(spp), "seed": int(seed)},
        }


@dataclasses.dataclass(frozen=True)
class ViewDistribution:
    """The paper's camera view distribution (App. C), with configurable ranges.

    θ and φ are drawn independently and uniformly from their ranges (degrees).
    """

    theta_range: tuple[float, float] = PAPER_THETA_RANGE
    phi_range: tuple[float, float] = PAPER_PHI_RANGE
    radius: float = PAPER_RADIUS
    focal_mm: float = PAPER_FOCAL_MM
    film_mm: float = PAPER_FILM_MM

    def __post_init__(self) -> None:
        for name in ("theta_range", "phi_range"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"view distribution {name} must be finite with low <= high, got {(lo, hi)}")
        if self.theta_range[0] < -90 or self.theta_range[1] > 90:
            raise ValueError(f"view distribution theta_range must lie in [-90, 90], got {self.theta_range}")

    def sample(self, n: int, seed: int, resolution: int | tuple[int, int] = 256) -> list[Camera]:
        """``n`` cameras drawn with ``numpy.random.default_rng(seed)``: same seed, same cameras."""
        rng = np.random.default_rng(seed)
        thetas = rng.uniform(*self.theta_range, size=n)
        phis = rng.uniform(*self.phi_range, size=n)
        return [Camera.orbit(float(t), float(p), resolution, self.radius, self.focal_mm, self.film_mm)
                for t, p in zip(thetas, phis)]
